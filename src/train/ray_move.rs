//! Fitting a network that moves a fill along its ray (the learned row and hole fills,
//! [`crate::decode::row_fill`], [`crate::decode::hole_fill`]): samples of what the network
//! sees, the fill's depth and the true depth; the network fitted to the mean absolute error
//! in meters (what the user's depth is scored by), with Adam and a cosine-decayed rate.

use serde::Serialize;

use crate::decode::row_fill::{MAX_MOVE, moved};
use crate::util::mlp::{Adam, Mlp};
use crate::util::rng::Rng;

/// Pixels with what the network sees, the fill it moves and what it should give, each with
/// its weight in the loss.
#[derive(Default)]
pub struct Samples {
    pub features: usize,
    pub x: Vec<f32>,
    pub reference: Vec<f32>,
    pub truth: Vec<f32>,
    pub weight: Vec<f32>,
}

impl Samples {
    pub fn len(&self) -> usize {
        self.truth.len()
    }

    pub fn is_empty(&self) -> bool {
        self.truth.is_empty()
    }

    pub fn push(&mut self, features: &[f32], reference: f32, truth: f32) {
        self.x.extend_from_slice(features);
        self.reference.push(reference);
        self.truth.push(truth);
        self.weight.push(1.0);
    }

    pub fn append(&mut self, other: Samples) {
        self.features = other.features;
        self.x.extend(other.x);
        self.reference.extend(other.reference);
        self.truth.extend(other.truth);
        self.weight.extend(other.weight);
    }

    /// Mean absolute error of the fill, in meters.
    pub fn fill_mae(&self) -> f64 {
        let sum: f64 = (self.reference.iter().zip(&self.truth))
            .map(|(r, t)| f64::from((r - t).abs()))
            .sum();
        sum / self.len().max(1) as f64
    }

    /// `groups` in one set, each group's samples weighted by the inverse of its fill's error,
    /// so that each group counts by its error relative to the fill's (the mean weight is 1):
    /// a group of large errors does not buy its gain with the others'.
    pub fn balanced(groups: Vec<Samples>) -> Samples {
        let scale: Vec<f64> = groups
            .iter()
            .map(|g| 1.0 / g.fill_mae().max(1e-3))
            .collect();
        let n: f64 = groups.iter().map(|g| g.len() as f64).sum();
        let mean = (groups.iter().zip(&scale))
            .map(|(g, s)| g.len() as f64 * s)
            .sum::<f64>()
            / n.max(1.0);
        let mut all = Samples::default();
        for (mut g, s) in groups.into_iter().zip(scale) {
            g.weight.iter_mut().for_each(|w| *w *= (s / mean) as f32);
            all.append(g);
        }
        all
    }
}

/// At most `n` of `order`, drawn with `rng` and kept in their order (all of them when there
/// are no more than `n`).
pub fn pick(mut order: Vec<usize>, n: usize, rng: &mut Rng) -> Vec<usize> {
    if n < order.len() {
        shuffle(&mut order, rng);
        order.truncate(n);
        order.sort_unstable();
    }
    order
}

pub fn shuffle(v: &mut [usize], rng: &mut Rng) {
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

/// The correction network fitted to `samples` (mean weighted absolute error);
/// `progress(epoch, mean training loss, network)` after each epoch.
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
                let (err, weight) = (pred - samples.truth[i], samples.weight[i]);
                loss_sum += f64::from(weight * err.abs());
                let inside = o.abs() < MAX_MOVE;
                grad.push(if inside {
                    weight * err.signum() * pred / batch.len() as f32
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
