//! Training the learned row fill ([`crate::decode::row_fill`]): restored pixels of KITTI
//! training scans, each with its features, the edge-aware fill there and the true depth;
//! the network fitted to the mean absolute error in meters (what the user's depth is scored
//! by), with Adam and a cosine-decayed rate; judged on a drive left out of training.

use std::path::PathBuf;

use anyhow::Result;
use rayon::prelude::*;
use serde::Serialize;

use crate::decode::Sparsify;
use crate::decode::row_fill::{MAX_MOVE, Window, edge_aware_rows, moved, restored_features};
use crate::lidar::{self, AngleGrid, SensorProfile, Strategy};
use crate::model::data::{MAX_DEPTH_M, MIN_DEPTH_M};
use crate::util::mlp::{Adam, Mlp};
use crate::util::rng::{Rng, key_hash};

/// Restored pixels with what the network sees and what it should give.
#[derive(Default)]
pub struct Samples {
    pub features: usize,
    pub x: Vec<f32>,
    pub reference: Vec<f32>,
    pub truth: Vec<f32>,
}

impl Samples {
    pub fn len(&self) -> usize {
        self.truth.len()
    }

    pub fn is_empty(&self) -> bool {
        self.truth.is_empty()
    }

    fn push(&mut self, features: &[f32], reference: f32, truth: f32) {
        self.x.extend_from_slice(features);
        self.reference.push(reference);
        self.truth.push(truth);
    }

    fn append(&mut self, other: Samples) {
        self.features = other.features;
        self.x.extend(other.x);
        self.reference.extend(other.reference);
        self.truth.extend(other.truth);
    }
}

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
    let mut order: Vec<usize> = (0..restored.pixels.len())
        .filter(|&i| depth[restored.pixels[i]] > 0.0)
        .collect();
    if per_scan < order.len() {
        shuffle(&mut order, rng);
        order.truncate(per_scan);
        order.sort_unstable();
    }
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

fn shuffle(v: &mut [usize], rng: &mut Rng) {
    for i in (1..v.len()).rev() {
        v.swap(i, rng.below(i + 1));
    }
}

/// How the network is fitted.
#[derive(Debug, Clone, Serialize)]
pub struct TrainOptions {
    pub hidden: Vec<usize>,
    pub epochs: usize,
    pub batch: usize,
    pub lr: f32,
    pub seed: u64,
}

impl Default for TrainOptions {
    fn default() -> Self {
        TrainOptions {
            hidden: vec![64, 64],
            epochs: 4,
            batch: 256,
            lr: 2e-3,
            seed: 1,
        }
    }
}

/// The correction network fitted to `samples`; `progress(epoch, mean training loss,
/// network)` after each epoch.
pub fn train(
    samples: &Samples,
    opts: &TrainOptions,
    mut progress: impl FnMut(usize, f64, &Mlp),
) -> Mlp {
    let mut rng = Rng::new(opts.seed);
    let nf = samples.features;
    let sizes: Vec<usize> = std::iter::once(nf)
        .chain(opts.hidden.iter().copied())
        .chain([1])
        .collect();
    let mut net = Mlp::new(&sizes, &mut rng);
    let mut adam = Adam::new(&net);
    let n = samples.len();
    let steps_per_epoch = n.div_ceil(opts.batch);
    let total = (steps_per_epoch * opts.epochs).max(1);
    let mut step = 0;
    let mut order: Vec<usize> = (0..n).collect();
    let mut x = Vec::with_capacity(opts.batch * nf);
    for epoch in 0..opts.epochs {
        shuffle(&mut order, &mut rng);
        let mut loss_sum = 0.0f64;
        for batch in order.chunks(opts.batch) {
            x.clear();
            for &i in batch {
                x.extend_from_slice(&samples.x[i * nf..(i + 1) * nf]);
            }
            let acts = net.forward_kept(&x);
            let mut grad = Vec::with_capacity(batch.len());
            for (&i, &o) in batch.iter().zip(acts.output()) {
                let pred = moved(samples.reference[i], o);
                let err = pred - samples.truth[i];
                loss_sum += f64::from(err.abs());
                let inside = o.abs() < MAX_MOVE;
                grad.push(if inside {
                    err.signum() * pred / batch.len() as f32
                } else {
                    0.0
                });
            }
            let grads = net.backward(&acts, &grad);
            let lr =
                opts.lr * 0.5 * (1.0 + (std::f32::consts::PI * step as f32 / total as f32).cos());
            adam.step(&mut net, &grads, lr);
            step += 1;
        }
        progress(epoch, loss_sum / n.max(1) as f64, &net);
    }
    net
}

/// Mean absolute error in meters, near (true depth <= 30 m) and far, of the fill and of the
/// corrected fill over `samples`.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Mae {
    pub pixels_near: usize,
    pub pixels_far: usize,
    pub fill: [f64; 3],
    pub corrected: [f64; 3],
}

pub fn mae(samples: &Samples, net: &Mlp) -> Mae {
    let moves = net.forward(&samples.x);
    let mut m = Mae::default();
    let mut sums = [[0.0f64; 2]; 2];
    for ((&r, &t), o) in samples.reference.iter().zip(&samples.truth).zip(moves) {
        let far = usize::from(t > 30.0);
        sums[far][0] += f64::from((r - t).abs());
        sums[far][1] += f64::from((moved(r, o) - t).abs());
        if far == 1 {
            m.pixels_far += 1;
        } else {
            m.pixels_near += 1;
        }
    }
    let (nn, nf) = (m.pixels_near.max(1) as f64, m.pixels_far.max(1) as f64);
    let all = (m.pixels_near + m.pixels_far).max(1) as f64;
    for (j, slot) in [&mut m.fill, &mut m.corrected].into_iter().enumerate() {
        *slot = [
            (sums[0][j] + sums[1][j]) / all,
            sums[0][j] / nn,
            sums[1][j] / nf,
        ];
    }
    m
}
