//! `diagnose/two-recordings/100x64x512`: the diagnosis of two 100-scan
//! recordings (HDL-64E at 64 x 512; sim = ideal scene 5, real = `realistic`
//! scene 6): features of every scan, the drop-rate tests, the forward selection
//! of drop models, the range-residual fits and the report files. Scans are
//! ray-cast first (not timed). The command-line number (MCAP reading and
//! projection included) is in BENCHMARKS.md.
//!
//! `cargo bench --bench diagnose`

use std::time::Instant;

use rangegan_mcap::diagnose::features::{FeatureOptions, ScanFeatures};
use rangegan_mcap::diagnose::{DiagnoseOptions, diagnose};
use rangegan_mcap::lidar::SensorProfile;
use rangegan_mcap::physics::{Physics, Preset};
use rangegan_mcap::sim::{SceneConfig, Simulator};
use rayon::prelude::*;

const SCANS: u32 = 100;

fn images(seed: u64, physics: &Physics) -> Vec<rangegan_mcap::lidar::RangeImage> {
    let sim = Simulator::new(
        SceneConfig {
            seed,
            duration_s: 0.1 * SCANS as f32 + 0.5,
            ..Default::default()
        },
        SensorProfile::kitti_hdl64e().with_columns(512),
    );
    (0..SCANS)
        .into_par_iter()
        .map(|i| {
            let mut scan = sim.scan(i);
            physics.apply(&mut scan, seed);
            scan.image
        })
        .collect()
}

fn main() {
    let sim_images = images(5, &Physics::ideal());
    let real_images = images(6, &Preset::Realistic.config().effects());
    let dir = std::env::temp_dir().join(format!("rangegan-diagnose-bench-{}", std::process::id()));
    for run in 0..3 {
        let t0 = Instant::now();
        let features = |imgs: &[rangegan_mcap::lidar::RangeImage]| -> Vec<ScanFeatures> {
            imgs.par_iter()
                .map(|i| ScanFeatures::from_image(i, &FeatureOptions::default()))
                .collect()
        };
        let (sim, real) = (features(&sim_images), features(&real_images));
        let t_features = t0.elapsed();
        let d = diagnose(
            &sim,
            &real,
            &Default::default(),
            "neighbour-fill",
            &DiagnoseOptions::default(),
        )
        .expect("diagnosis");
        let t_fit = t0.elapsed() - t_features;
        rangegan_mcap::report::write(&dir, &d, &Default::default()).expect("report");
        let total = t0.elapsed();
        println!(
            "diagnose/two-recordings/100x64x512 run {run}: features {:.2} s, stats + fits {:.2} s, total with report {:.2} s ({} threads); effects [{}]",
            t_features.as_secs_f64(),
            t_fit.as_secs_f64(),
            total.as_secs_f64(),
            rayon::current_num_threads(),
            d.report
                .effects
                .iter()
                .map(|e| e.id.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}
