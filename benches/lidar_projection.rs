//! Speed of the `lidar` module on one full-resolution KITTI scan (~124k points):
//! projection per strategy at 64x2048, sensor estimation, and resampling. Reads
//! `../shared/real_lidar/semantickitti_ssv3/000000.bin` when it exists, else
//! generates a scan with the same layout (64 rings x 2010 points in KITTI ring
//! order). Also the fill of a 64x512 grid from a random 10 % of its returns
//! (`fill_scattered`: IDW and local surfaces), and rows restored from 16 of 64 (the
//! edge-aware fill and the learned correction on it). Plain timing harness (no
//! criterion), single-threaded like one scan in `convert`:
//!
//! `cargo bench --bench lidar_projection`
//!
//! Prints `group/case/size: wall median ms (min .. max) over N runs; CPU ms/run`.
//! Numbers are recorded in `docs/lidar.md`.

use std::hint::black_box;
use std::path::Path;
use std::time::Instant;

use rangegan_mcap::decode::Sparsify;
use rangegan_mcap::decode::row_fill::{RowFill, edge_aware_rows};
use rangegan_mcap::lidar::{
    Interpolation, Scan, ScatterFill, SensorProfile, Strategy, estimate_profile, fill_scattered,
    kitti, project, resample_image,
};

/// CPU seconds used by this process so far (user + system), from `/proc/self/stat`;
/// on a shared machine this is the fair single-core cost.
fn cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    let rest = &stat[stat.rfind(')')? + 2..];
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let ticks: f64 = fields.get(11)?.parse::<f64>().ok()? + fields.get(12)?.parse::<f64>().ok()?;
    Some(ticks / 100.0) // USER_HZ is 100 on Linux
}

fn time_runs<T>(label: &str, runs: u32, mut f: impl FnMut() -> T) {
    black_box(f()); // warm up
    let cpu0 = cpu_seconds();
    let mut ms: Vec<f64> = (0..runs)
        .map(|_| {
            let t = Instant::now();
            black_box(f());
            t.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    let cpu = cpu0
        .zip(cpu_seconds())
        .map(|(a, b)| (b - a) * 1e3 / f64::from(runs));
    ms.sort_by(f64::total_cmp);
    let cpu = cpu.map_or(String::new(), |c| format!("; CPU {c:.1} ms/run"));
    println!(
        "{label}: wall median {:.1} ms (min {:.1} .. max {:.1}) over {runs} runs{cpu}",
        ms[ms.len() / 2],
        ms[0],
        ms[ms.len() - 1]
    );
}

/// The real scan, or a generated one in the same layout.
fn kitti_scan() -> (Scan, &'static str) {
    let path = Path::new("../shared/real_lidar/semantickitti_ssv3/000000.bin");
    if let Ok(scan) = kitti::read_scan(path, None) {
        return (scan, "real KITTI semantickitti_ssv3/000000.bin");
    }
    let table = SensorProfile::kitti_hdl64e().elevation_deg;
    let per_ring = 2010;
    let mut xyz = Vec::with_capacity(table.len() * per_ring);
    for (ring, e) in table.iter().enumerate() {
        for k in 0..per_ring {
            // Each ring starts just left of ahead and sweeps counter-clockwise.
            let az = 0.001 + k as f32 * std::f32::consts::TAU / per_ring as f32;
            let r = 4.0 + 30.0 * (0.5 + 0.5 * (3.0 * az + ring as f32).sin());
            let e = e.to_radians();
            xyz.push([r * e.cos() * az.cos(), r * e.cos() * az.sin(), r * e.sin()]);
        }
    }
    (Scan::from_xyz(xyz), "generated KITTI-like scan")
}

fn main() {
    let (scan, what) = kitti_scan();
    println!("input: {what}, {} points", scan.len());
    let runs = 30;
    let profile = SensorProfile::kitti_hdl64e().with_columns(2048);
    for (name, strategy) in [
        ("ring-order", Strategy::RingOrder),
        ("auto", Strategy::Auto),
        ("spherical", Strategy::Spherical),
    ] {
        time_runs(&format!("lidar/project/{name}/64x2048"), runs, || {
            project(&scan, &profile, strategy).map(|img| img.valid_count())
        });
    }
    time_runs("lidar/estimate/ring-order/1-scan", runs, || {
        estimate_profile(std::slice::from_ref(&scan)).map(|e| e.columns)
    });
    let small = match project(
        &scan,
        &SensorProfile::kitti_hdl64e().with_columns(512),
        Strategy::RingOrder,
    ) {
        Ok(img) => img,
        Err(e) => {
            eprintln!("cannot project the input: {e}");
            return;
        }
    };
    let fine = small.angles.resized(64, 2048);
    time_runs("lidar/grid-resize/64x512-to-128x2048", runs, || {
        small.angles.resized(128, 2048)
    });
    for m in [Interpolation::Nearest, Interpolation::Bilinear] {
        time_runs(
            &format!("lidar/resample/{}/64x512-to-64x2048", m.name()),
            runs,
            || resample_image(&small, &fine, m).valid_count(),
        );
    }
    // A fixed hash of the pixel index picks 10 % of the returns.
    let observed: Vec<f32> = small
        .range_m
        .iter()
        .enumerate()
        .map(|(k, d)| {
            let hash = (k as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 54;
            if hash.is_multiple_of(10) { *d } else { 0.0 }
        })
        .collect();
    let surfaces = ScatterFill::Surfaces {
        guide: None,
        guide_jump: 0.3,
    };
    for (name, how) in [("idw", ScatterFill::Idw), ("surfaces", surfaces)] {
        time_runs(
            &format!("lidar/fill-scattered/{name}/64x512-10pct"),
            runs,
            || fill_scattered(&observed, &small.angles, how).len(),
        );
    }
    // Rows restored from 16 of 64: the edge-aware fill, then the learned correction on it.
    let kept = Sparsify::kept_rows(16, 64);
    time_runs(
        "decode/restore-rows/edge-aware/64x512-16-lines",
        runs,
        || edge_aware_rows(&small.angles, &small.range_m, &kept).len(),
    );
    let reference = edge_aware_rows(&small.angles, &small.range_m, &kept);
    time_runs(
        "decode/restore-rows/learned-correction/64x512-16-lines",
        runs,
        || {
            RowFill::shipped()
                .refine(&small.range_m, &reference, &small.angles, &kept)
                .len()
        },
    );
}
