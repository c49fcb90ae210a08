//! Samples for the learned row fill ([`crate::decode::row_fill`]): restored pixels of KITTI
//! training scans, each with its features, the edge-aware fill there and the true depth,
//! fitted by [`super::ray_move`]; judged on a drive left out of training.

use std::path::PathBuf;

use anyhow::Result;
use rayon::prelude::*;

use super::ray_move::{Samples, pick};
use crate::decode::Sparsify;
use crate::decode::row_fill::{Window, edge_aware_rows, restored_features};
use crate::lidar::{self, AngleGrid, SensorProfile, Strategy};
use crate::model::data::{MAX_DEPTH_M, MIN_DEPTH_M};
use crate::util::rng::{Rng, key_hash};

/// A KITTI scan on the model grid (HDL-64E, 64 x 512): its angles and its depths (0 outside
/// the model's depth range or where no return was measured).
pub fn kitti_depth(path: &std::path::Path) -> Result<(AngleGrid, Vec<f32>)> {
    let profile = SensorProfile::kitti_hdl64e().with_columns(512);
    let scan = lidar::kitti::read_bin(path)?;
    let image = lidar::project(&scan, &profile, Strategy::Auto)?;
    let depth = image
        .range_m
        .iter()
        .map(|&r| {
            if (MIN_DEPTH_M..=MAX_DEPTH_M).contains(&r) {
                r
            } else {
                0.0
            }
        })
        .collect();
    Ok((image.angles, depth))
}

/// Up to `per_scan` restored pixels with a true return from each scan and each number of
/// kept lines (all of them when `per_scan` is `usize::MAX`), drawn with a seed from the
/// scan's position in `files` (deterministic whatever the thread count).
pub fn collect(
    window: Window,
    files: &[PathBuf],
    lines: &[usize],
    per_scan: usize,
    seed: u64,
) -> Result<Samples> {
    let parts: Vec<Result<Samples>> = files
        .par_iter()
        .enumerate()
        .map(|(i, f)| {
            let (grid, depth) = kitti_depth(f)?;
            let mut out = Samples::default();
            for &n in lines {
                let mut rng = Rng::new(key_hash(&[seed, i as u64, n as u64]));
                out.append(scan_samples(window, &grid, &depth, n, per_scan, &mut rng));
            }
            Ok(out)
        })
        .collect();
    let mut all = Samples::default();
    for p in parts {
        all.append(p?);
    }
    Ok(all)
}

fn scan_samples(
    window: Window,
    grid: &AngleGrid,
    depth: &[f32],
    lines: usize,
    per_scan: usize,
    rng: &mut Rng,
) -> Samples {
    let kept = Sparsify::kept_rows(lines, grid.height);
    let reference = edge_aware_rows(grid, depth, &kept);
    let restored = restored_features(window, depth, &reference, grid, &kept);
    let nf = window.features();
    let with_truth = (0..restored.pixels.len())
        .filter(|&i| depth[restored.pixels[i]] > 0.0)
        .collect();
    let order = pick(with_truth, per_scan, rng);
    let mut out = Samples {
        features: nf,
        ..Samples::default()
    };
    for i in order {
        let k = restored.pixels[i];
        out.push(
            &restored.x[i * nf..(i + 1) * nf],
            restored.start[i],
            depth[k],
        );
    }
    out
}
