//! The spatial-latent model on held-out real KITTI scans (never trained or tuned on), scored
//! on every pixel the user gets:
//!
//! - x_d against the measured returns it saw (relative L1);
//! - completion: holes of every kind cut into each scan, depth (x_d) in the holes against
//!   interpolating along the rows and along the columns (MAE in metres, and the ratio to the
//!   better of the two);
//! - restoration 16 -> 64 beams on the scan's own columns, against per-column linear
//!   interpolation;
//! - x_n inside medium patches the decoder could not see: NLL of the true mask against each
//!   beam's drop rate outside the patches.
//!
//! `--set full-resolution` (default) is the six full-resolution scans of `semantickitti_ssv3`
//! and `patchworkpp` at 2048 columns; `--set heldout` the 26 scans of SemanticKITTI 00 and 07
//! stored at every fourth point, at 512 columns. Settings are chosen on `--set validation`
//! (every third scan of the drive held out of training, 512 columns) and `--set
//! validation-full-resolution` (every fourth of the full-resolution drive's held-out frames).
//!
//!     cargo run --release --example spatial_eval -- [--data ../shared/real_lidar]
//!         [--set full-resolution|heldout] [--model DIR]

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use burn::tensor::Device;
use rangegan_mcap::decode::Sparsify;
use rangegan_mcap::lidar::RangeImage;
use rangegan_mcap::lidar::holes::HoleKind;
use rangegan_mcap::model::data::{EVALUATION_FOLDERS, kitti_heldout_files, kitti_validation_split};
use rangegan_mcap::model::spatial::decode::{blend_with_row_rates, decode, rays_of};
use rangegan_mcap::model::spatial::{Ray, SpatialModel};
use rangegan_mcap::train::spatial::data;
use rangegan_mcap::train::spatial::validate::{self, bernoulli_nll, row_keep_rates};
use rangegan_mcap::util::rng::Rng;
use rayon::prelude::*;

#[path = "common/holed.rs"]
#[allow(dead_code)] // the convert helpers are for the examples that run the binary
mod holed;

struct Args {
    data: PathBuf,
    set: String,
    model: Option<PathBuf>,
}

fn args() -> Result<Args> {
    let mut a = Args {
        data: PathBuf::from("../shared/real_lidar"),
        set: "full-resolution".into(),
        model: None,
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let mut value = || it.next().with_context(|| format!("{flag} needs a value"));
        match flag.as_str() {
            "--data" => a.data = value()?.into(),
            "--set" => a.set = value()?,
            "--model" => a.model = Some(value()?.into()),
            other => bail!("unknown flag {other}"),
        }
    }
    Ok(a)
}

/// Mean of absolute errors over the true returns where `at` holds.
#[derive(Default, Clone, Copy)]
struct Mae(f64, usize);

impl Mae {
    fn add(&mut self, v: f64) {
        self.0 += v;
        self.1 += 1;
    }
    fn merge(&mut self, o: Mae) {
        self.0 += o.0;
        self.1 += o.1;
    }
    fn get(&self) -> f64 {
        self.0 / self.1.max(1) as f64
    }
}

/// Weights of x_n against the scan's own per-beam rates that are scored.
const WEIGHTS: [f32; 5] = [0.0, 0.25, 0.5, 0.75, 1.0];

/// Scores of one scan: [model, rows, columns] MAE per hole kind; x_d rel L1; restoration
/// [model, column linear]; x_n [model, row rate] NLL in medium holes; x_n blended with the
/// scan's own rates at each of [`WEIGHTS`], in the holes and on the whole scan.
struct ScanScore {
    holes: Vec<[Mae; 3]>,
    seen: Mae,
    restore: [Mae; 2],
    drop: [Mae; 2],
    blend_holes: [Mae; 5],
    blend_whole: [Mae; 5],
}

fn score(model: &SpatialModel, image: &RangeImage, index: usize) -> ScanScore {
    let host = model.host();
    let (h, w) = (image.height, image.width);
    let truth = &image.range_m;
    let run = |rays: &[Ray]| decode(&host, rays, &image.angles);
    let all_rays = rays_of(truth);
    let full = run(&all_rays);
    let mut seen = Mae::default();
    for k in (0..h * w).filter(|&k| truth[k] > 0.0) {
        seen.add(((full.depth_m[k] - truth[k]) / truth[k]).abs() as f64);
    }
    let mut blend_whole = [Mae::default(); 5];
    for (m, &wt) in blend_whole.iter_mut().zip(&WEIGHTS) {
        let mut p = full.drop_prob.clone();
        blend_with_row_rates(&mut p, &all_rays, w, wt);
        for k in 0..h * w {
            m.add(bernoulli_nll(1.0 - p[k], truth[k] > 0.0));
        }
    }
    let mut blend_holes = [Mae::default(); 5];
    let mut holes = Vec::new();
    let mut drop = [Mae::default(); 2];
    for (n, kind) in HoleKind::ALL.iter().enumerate() {
        let cut = kind.cut(truth, h, w, &mut Rng::keyed(index as u64, n as u64));
        let observed: Vec<f32> = (0..h * w)
            .map(|k| if cut[k] { 0.0 } else { truth[k] })
            .collect();
        let out = run(&rays_of(&observed));
        let rows = holed::interpolate(&observed, h, w, true);
        let cols = holed::interpolate(&observed, h, w, false);
        let mut m = [Mae::default(); 3];
        for k in (0..h * w).filter(|&k| cut[k] && truth[k] > 0.0) {
            for (e, d) in m.iter_mut().zip([out.depth_m[k], rows[k], cols[k]]) {
                e.add((d - truth[k]).abs() as f64);
            }
        }
        if *kind == HoleKind::Medium {
            // x_n where the decoder cannot see the answer: the patches are unknown to it.
            let rays = validate::unknown_in(&observed, &cut);
            let out = run(&rays);
            for (m, &wt) in blend_holes.iter_mut().zip(&WEIGHTS) {
                let mut p = out.drop_prob.clone();
                blend_with_row_rates(&mut p, &rays, w, wt);
                for k in (0..h * w).filter(|&k| cut[k]) {
                    m.add(bernoulli_nll(1.0 - p[k], truth[k] > 0.0));
                }
            }
            let keep = row_keep_rates(&observed, &cut, h, w);
            for k in (0..h * w).filter(|&k| cut[k]) {
                let ret = truth[k] > 0.0;
                drop[0].add(bernoulli_nll(1.0 - out.drop_prob[k], ret));
                drop[1].add(bernoulli_nll(keep[k / w], ret));
            }
        }
        holes.push(m);
    }
    // Restoration: 16 of 64 beams kept; the others unknown to the model.
    let kept = Sparsify::kept_rows(16, h);
    let rays: Vec<Ray> = rays_of(truth)
        .into_iter()
        .enumerate()
        .map(|(k, r)| {
            if kept.contains(&(k / w)) {
                r
            } else {
                Ray::Unknown
            }
        })
        .collect();
    let out = run(&rays);
    let sparse: Vec<f32> = (0..h * w)
        .map(|k| {
            if kept.contains(&(k / w)) {
                truth[k]
            } else {
                0.0
            }
        })
        .collect();
    let linear = holed::interpolate(&sparse, h, w, false);
    let mut restore = [Mae::default(); 2];
    for k in (0..h * w).filter(|&k| !kept.contains(&(k / w)) && truth[k] > 0.0) {
        restore[0].add((out.depth_m[k] - truth[k]).abs() as f64);
        restore[1].add((linear[k] - truth[k]).abs() as f64);
    }
    ScanScore {
        holes,
        seen,
        restore,
        drop,
        blend_holes,
        blend_whole,
    }
}

fn main() -> Result<()> {
    let a = args()?;
    let device = Device::flex();
    let model = match &a.model {
        Some(dir) => SpatialModel::load(dir, &device)?,
        None => SpatialModel::shipped(&device)?,
    };
    let (files, columns) = match a.set.as_str() {
        "full-resolution" => {
            let mut f = Vec::new();
            for folder in EVALUATION_FOLDERS {
                let dir = a.data.join(folder);
                let mut bins: Vec<PathBuf> = std::fs::read_dir(&dir)
                    .with_context(|| format!("failed to list '{}'", dir.display()))?
                    .filter_map(|e| e.ok().map(|e| e.path()))
                    .filter(|p| p.extension().is_some_and(|e| e == "bin"))
                    .collect();
                bins.sort();
                f.extend(bins);
            }
            (f, 2048)
        }
        "heldout" => (kitti_heldout_files(&a.data)?, 512),
        // Where the x_n weight is chosen: the drive held out of training, never evaluated on.
        "validation" => (
            kitti_validation_split(&a.data, &["kitti_raw_drive_g".to_string()])?
                .1
                .into_iter()
                .step_by(3)
                .collect(),
            512,
        ),
        "validation-full-resolution" => (Vec::new(), 2048),
        other => bail!(
            "--set {other}: full-resolution, heldout, validation or validation-full-resolution"
        ),
    };
    let images = if a.set == "validation-full-resolution" {
        // The full-resolution drive's last frames, held out of training: every fourth.
        let (_, held_out) = data::fullres_sources(&a.data)?;
        held_out
            .scans
            .iter()
            .step_by(4)
            .map(|range| {
                let mut image = RangeImage::empty(held_out.angles.clone());
                image.range_m = range.clone();
                image
            })
            .collect()
    } else {
        holed::project_all(&files, columns)?
    };
    let started = std::time::Instant::now();
    let scores: Vec<ScanScore> = images
        .par_iter()
        .enumerate()
        .map(|(i, img)| score(&model, img, i))
        .collect();
    eprintln!(
        "{} scans of {} at {columns} columns, model {} ({:.0} s)",
        images.len(),
        a.set,
        model.source,
        started.elapsed().as_secs_f64()
    );
    let sum = |f: &dyn Fn(&ScanScore) -> Mae| {
        let mut m = Mae::default();
        for s in &scores {
            m.merge(f(s));
        }
        m.get()
    };
    println!("| measure | spatial model | baseline | ratio |");
    println!("|---|---|---|---|");
    println!(
        "| x_d relative L1 at the returns it saw | {:.4} | | |",
        sum(&|s| s.seen)
    );
    for (n, kind) in HoleKind::ALL.iter().enumerate() {
        let [m, r, c] = [0, 1, 2].map(|i| sum(&|s: &ScanScore| s.holes[n][i]));
        println!(
            "| completion, {} holes: MAE m (rows {r:.3}, columns {c:.3}) | {m:.3} | {:.3} | {:.2}x |",
            kind.name(),
            r.min(c),
            m / r.min(c)
        );
    }
    let [m, l] = [0, 1].map(|i| sum(&|s: &ScanScore| s.restore[i]));
    println!(
        "| restoration 16 -> 64 beams, MAE m (per-column linear) | {m:.3} | {l:.3} | {:.2}x |",
        m / l
    );
    let [m, r] = [0, 1].map(|i| sum(&|s: &ScanScore| s.drop[i]));
    println!(
        "| x_n NLL inside medium patches (per-beam rate) | {m:.4} | {r:.4} | {:.2}x |",
        m / r
    );
    for (i, wt) in WEIGHTS.iter().enumerate() {
        let hole = sum(&|s: &ScanScore| s.blend_holes[i]);
        let whole = sum(&|s: &ScanScore| s.blend_whole[i]);
        println!(
            "| raydrop_prob = {wt} x_n + {} scan's own per-beam rate: NLL in medium holes / whole scan | {hole:.4} / {whole:.4} | | |",
            1.0 - wt
        );
    }
    Ok(())
}
