//! A classifier two-sample test (C2ST) for range images: can a classifier tell two sets of
//! scans apart? Accuracy near 0.5 means it cannot; near 1 that they differ at a glance.
//!
//! Each scan becomes a vector of texture statistics that a person uses to tell a LiDAR scan
//! from a blob: drop rate and depth per band of rows, the depth histogram, how smoothly depth
//! changes between neighbouring beams and columns (road rings and walls are smooth, blobs and
//! salt noise are not), and how ray drops cluster. An L2-regularised logistic regression is
//! scored by stratified k-fold cross-validation on equal-sized sets, repeated over seeded
//! splits. SWD of image patches ranks structureless samples close to real ones; this test is
//! checked against blurred real scans, which it must tell apart. Where the classifier tells
//! every candidate apart perfectly, [`frechet_distance`] on the same statistics still ranks them.
//!
//! Images are in network units: 2 x_d - 1 for a return, -1 for a dropped ray.

use nalgebra::{DMatrix, DVector};

use super::data::DROPPED;
use crate::util::math::softplus;
use crate::util::rng::Rng;

/// Row bands the per-band statistics are taken over.
const BANDS: usize = 4;

/// Bins of the return depth histogram over [-1, 1].
const BINS: usize = 8;

/// The texture statistics of one `h x w` image (see the module doc).
pub fn texture_features(x: &[f32], h: usize, w: usize) -> Vec<f64> {
    assert_eq!(x.len(), h * w, "image size");
    let ret = |r: usize, c: usize| -> Option<f64> {
        let v = x[r * w + c % w];
        (v > DROPPED).then_some(f64::from(v))
    };
    let mut f = Vec::with_capacity(4 * BANDS + BINS + 14);
    // Per band of rows: drop rate, mean and spread of the returns.
    for band in 0..BANDS {
        let rows = band * h / BANDS..((band + 1) * h / BANDS).max(band * h / BANDS + 1);
        let values: Vec<f64> = rows
            .flat_map(|r| (0..w).map(move |c| (r, c)))
            .filter_map(|(r, c)| ret(r, c))
            .collect();
        let n = (h / BANDS).max(1) * w;
        f.push(1.0 - values.len() as f64 / n as f64);
        let (mean, sd) = mean_sd(&values);
        f.push(mean);
        f.push(sd);
    }
    // Histogram of the returns' inverse depth.
    let mut hist = [0f64; BINS];
    let mut returns = 0usize;
    for v in x.iter().filter(|v| **v > DROPPED) {
        let bin = (((v + 1.0) * 0.5 * BINS as f32) as usize).min(BINS - 1);
        hist[bin] += 1.0;
        returns += 1;
    }
    f.extend(hist.iter().map(|c| c / returns.max(1) as f64));
    // Smoothness along a column (beam to beam) and along a row (column to column).
    for (dr, dc) in [(1usize, 0usize), (0, 1)] {
        let (mut first, mut second) = (Vec::new(), Vec::new());
        for r in 0..h.saturating_sub(2 * dr) {
            for c in 0..w {
                let (a, b, d) = (ret(r, c), ret(r + dr, c + dc), ret(r + 2 * dr, c + 2 * dc));
                if let (Some(a), Some(b)) = (a, b) {
                    first.push((b - a).abs());
                    if let Some(d) = d {
                        second.push((d - 2.0 * b + a).abs());
                    }
                }
            }
        }
        f.push(mean_sd(&first).0);
        f.push(share(&first, |d| d < 0.01));
        f.push(share(&first, |d| d > 0.1));
        f.push(mean_sd(&second).0);
        f.push(share(&second, |d| d < 0.005));
    }
    // How ray drops cluster: isolated drops (salt noise), and drop boundaries per pixel.
    let dropped = |r: usize, c: usize| ret(r, c).is_none();
    let (mut isolated, mut drops, mut across, mut down) = (0usize, 0usize, 0usize, 0usize);
    for r in 0..h {
        for c in 0..w {
            let d = dropped(r, c);
            if d {
                drops += 1;
                let up = r == 0 || !dropped(r - 1, c);
                let below = r + 1 == h || !dropped(r + 1, c);
                if up && below && !dropped(r, c + 1) && !dropped(r, c + w - 1) {
                    isolated += 1;
                }
            }
            across += usize::from(d != dropped(r, c + 1));
            if r + 1 < h {
                down += usize::from(d != dropped(r + 1, c));
            }
        }
    }
    let pixels = (h * w) as f64;
    f.push(isolated as f64 / drops.max(1) as f64);
    f.push(across as f64 / pixels);
    f.push(down as f64 / pixels);
    f.push((1.0 + drops as f64 / across.max(1) as f64).ln()); // mean run length of drops
    f
}

/// Per feature: the mean of `set` and 1 / its standard deviation (0 for a constant feature).
fn standardiser(set: &[&Vec<f64>]) -> (Vec<f64>, Vec<f64>) {
    let (d, n) = (set[0].len(), set.len() as f64);
    let mean: Vec<f64> = (0..d)
        .map(|j| set.iter().map(|x| x[j]).sum::<f64>() / n)
        .collect();
    let scale = (0..d)
        .map(|j| {
            let var = set.iter().map(|x| (x[j] - mean[j]).powi(2)).sum::<f64>() / n;
            if var > 1e-24 { 1.0 / var.sqrt() } else { 0.0 }
        })
        .collect();
    (mean, scale)
}

/// A seeded shuffle of `0..n` (Fisher-Yates).
fn permutation(rng: &mut Rng, n: usize) -> Vec<usize> {
    let mut idx: Vec<usize> = (0..n).collect();
    for i in (1..n).rev() {
        idx.swap(i, rng.below(i + 1));
    }
    idx
}

fn mean_sd(v: &[f64]) -> (f64, f64) {
    if v.is_empty() {
        return (0.0, 0.0);
    }
    let n = v.len() as f64;
    let mean = v.iter().sum::<f64>() / n;
    let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n;
    (mean, var.sqrt())
}

fn share(v: &[f64], pred: impl Fn(f64) -> bool) -> f64 {
    v.iter().filter(|x| pred(**x)).count() as f64 / v.len().max(1) as f64
}

/// Settings of [`c2st`].
#[derive(Debug, Clone, Copy)]
pub struct C2stConfig {
    pub folds: usize,
    /// Seeded repetitions of the subsampling and the fold split.
    pub repeats: usize,
    /// L2 weight of the logistic regression (on standardised features).
    pub l2: f64,
    pub seed: u64,
}

impl Default for C2stConfig {
    fn default() -> Self {
        Self {
            folds: 5,
            repeats: 5,
            l2: 1.0,
            seed: 0,
        }
    }
}

/// Cross-validated accuracy over the repetitions: mean and standard deviation.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct C2stReport {
    pub accuracy: f64,
    pub std: f64,
    /// Cross-validated mean log-loss of the classifier in nats: ln 2 = 0.69 where it cannot
    /// tell the sets apart, towards 0 the more surely it can; keeps ranking sets where the
    /// accuracy has reached 1.
    pub log_loss: f64,
    /// Scans per set after subsampling to equal sizes.
    pub per_set: usize,
}

/// The two-sample test between feature sets `a` and `b` (rows of [`texture_features`]).
pub fn c2st(a: &[Vec<f64>], b: &[Vec<f64>], cfg: &C2stConfig) -> C2stReport {
    let n = a.len().min(b.len());
    assert!(
        n >= cfg.folds.max(2),
        "too few scans for the two-sample test"
    );
    let mut rng = Rng::new(cfg.seed ^ 0xc257);
    let mut loss_sum = 0.0;
    let accs: Vec<f64> = (0..cfg.repeats.max(1))
        .map(|_| {
            let ia = permutation(&mut rng, a.len());
            let ib = permutation(&mut rng, b.len());
            // Stratified folds: the k-th scan of each (shuffled) set goes to fold k mod F.
            let mut correct = 0usize;
            for fold in 0..cfg.folds {
                let split = |idx: &[usize], set: &[Vec<f64>], test: bool| -> Vec<Vec<f64>> {
                    idx[..n]
                        .iter()
                        .enumerate()
                        .filter(|(k, _)| (k % cfg.folds == fold) == test)
                        .map(|(_, &i)| set[i].clone())
                        .collect()
                };
                let model = Logistic::fit(&split(&ia, a, false), &split(&ib, b, false), cfg.l2);
                // Signed so that a positive margin is a correct call.
                let margins = split(&ia, a, true)
                    .iter()
                    .map(|x| model.score(x))
                    .chain(split(&ib, b, true).iter().map(|x| -model.score(x)))
                    .collect::<Vec<f64>>();
                correct += margins.iter().filter(|m| **m > 0.0).count();
                loss_sum += margins.iter().map(|m| softplus(-m)).sum::<f64>();
            }
            correct as f64 / (2 * n) as f64
        })
        .collect();
    let (accuracy, std) = mean_sd(&accs);
    C2stReport {
        accuracy,
        std,
        log_loss: loss_sum / (accs.len() * 2 * n) as f64,
        per_set: n,
    }
}

/// Logistic regression on standardised features, fitted by Newton's method (IRLS).
struct Logistic {
    mean: Vec<f64>,
    scale: Vec<f64>,
    /// Bias first, then one weight per feature.
    weights: DVector<f64>,
}

impl Logistic {
    /// Fits P(set a | x); `a` is labelled 1, `b` 0.
    fn fit(a: &[Vec<f64>], b: &[Vec<f64>], l2: f64) -> Logistic {
        let d = a[0].len();
        let all: Vec<&Vec<f64>> = a.iter().chain(b).collect();
        let (mean, scale) = standardiser(&all);
        let mut model = Logistic {
            mean,
            scale,
            weights: DVector::zeros(d + 1),
        };
        let rows: Vec<DVector<f64>> = all.iter().map(|x| model.design(x)).collect();
        let labels: Vec<f64> = (0..all.len())
            .map(|i| if i < a.len() { 1.0 } else { 0.0 })
            .collect();
        for _ in 0..25 {
            let mut grad = DVector::zeros(d + 1);
            let mut hess = DMatrix::zeros(d + 1, d + 1);
            for (row, y) in rows.iter().zip(&labels) {
                let p = 1.0 / (1.0 + (-model.weights.dot(row)).exp());
                grad += row * (p - y);
                hess += row * row.transpose() * (p * (1.0 - p)).max(1e-9);
            }
            // The bias is not penalised.
            for j in 1..=d {
                grad[j] += l2 * model.weights[j];
                hess[(j, j)] += l2;
            }
            hess[(0, 0)] += 1e-9;
            let Some(step) = hess.lu().solve(&grad) else {
                break;
            };
            model.weights -= &step;
            if step.amax() < 1e-8 {
                break;
            }
        }
        model
    }

    fn design(&self, x: &[f64]) -> DVector<f64> {
        DVector::from_iterator(
            x.len() + 1,
            std::iter::once(1.0).chain(
                x.iter()
                    .zip(&self.mean)
                    .zip(&self.scale)
                    .map(|((v, m), s)| (v - m) * s),
            ),
        )
    }

    /// Log-odds of set `a`.
    fn score(&self, x: &[f64]) -> f64 {
        self.weights.dot(&self.design(x))
    }
}

/// The Fréchet distance between Gaussians fitted to two feature sets (as FID does for
/// Inception features), each feature first standardised by `reference`'s mean and spread. It
/// does not saturate where the classifier's accuracy reaches 1, so it ranks sets that are all
/// easy to tell from real scans.
pub fn frechet_distance(a: &[Vec<f64>], b: &[Vec<f64>], reference: &[Vec<f64>]) -> f64 {
    let d = reference[0].len();
    let (mean, scale) = standardiser(&reference.iter().collect::<Vec<_>>());
    let gaussian = |set: &[Vec<f64>]| -> (DVector<f64>, DMatrix<f64>) {
        let rows: Vec<DVector<f64>> = set
            .iter()
            .map(|x| DVector::from_iterator(d, (0..d).map(|j| (x[j] - mean[j]) * scale[j])))
            .collect();
        let m = rows.len() as f64;
        let mu = rows.iter().fold(DVector::zeros(d), |acc, r| acc + r) / m;
        let cov = rows.iter().fold(DMatrix::zeros(d, d), |acc, r| {
            let c = r - &mu;
            acc + &c * c.transpose()
        }) / (m - 1.0).max(1.0);
        (mu, cov)
    };
    let (mu_a, cov_a) = gaussian(a);
    let (mu_b, cov_b) = gaussian(b);
    let root_a = symmetric_sqrt(&cov_a);
    let cross = symmetric_sqrt(&(&root_a * &cov_b * &root_a));
    (mu_a - mu_b).norm_squared() + cov_a.trace() + cov_b.trace() - 2.0 * cross.trace()
}

/// The square root of a symmetric positive semi-definite matrix (negative eigenvalues from
/// rounding are taken as 0).
fn symmetric_sqrt(m: &DMatrix<f64>) -> DMatrix<f64> {
    let sym = (m + m.transpose()) * 0.5;
    let eigen = sym.symmetric_eigen();
    let roots = eigen.eigenvalues.map(|v| v.max(0.0).sqrt());
    &eigen.eigenvectors * DMatrix::from_diagonal(&roots) * eigen.eigenvectors.transpose()
}

/// A 3 x 3 box blur of the returns' inverse depth (drops stay where they are, and only
/// returns are averaged): the known-bad input a structure-aware measure must flag.
pub fn blur_returns(x: &[f32], h: usize, w: usize) -> Vec<f32> {
    let mut out = x.to_vec();
    for r in 0..h {
        for c in 0..w {
            if x[r * w + c] <= DROPPED {
                continue;
            }
            let (mut sum, mut count) = (0f32, 0f32);
            for rr in r.saturating_sub(1)..(r + 2).min(h) {
                for dc in [w - 1, 0, 1] {
                    let v = x[rr * w + (c + dc) % w];
                    if v > DROPPED {
                        sum += v;
                        count += 1.0;
                    }
                }
            }
            out[r * w + c] = sum / count;
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Smooth scans with a ground ramp against the same scans with every return replaced by
    /// noise of the same mean: the test tells them apart; two halves of one set it does not.
    #[test]
    fn the_test_separates_structure_from_noise_and_not_a_set_from_itself() {
        let (h, w) = (16, 64);
        let mut rng = Rng::new(7);
        let mut smooth = Vec::new();
        let mut noisy = Vec::new();
        for _ in 0..60 {
            let tilt = rng.uniform() * 0.2;
            let img: Vec<f32> = (0..h * w)
                .map(|k| {
                    let (r, c) = (k / w, k % w);
                    if rng.uniform() < 0.1 {
                        -1.0
                    } else {
                        -0.8 + 1.2 * r as f32 / h as f32 + tilt * (c as f32 / w as f32)
                    }
                })
                .collect();
            let mean = img.iter().filter(|v| **v > -1.0).sum::<f32>() / (h * w) as f32;
            let noise: Vec<f32> = img
                .iter()
                .map(|v| {
                    if *v > -1.0 {
                        (mean + rng.normal() * 0.3).clamp(-0.99, 1.0)
                    } else {
                        -1.0
                    }
                })
                .collect();
            smooth.push(texture_features(&img, h, w));
            noisy.push(texture_features(&noise, h, w));
        }
        let cfg = C2stConfig::default();
        let apart = c2st(&smooth, &noisy, &cfg);
        assert!(apart.accuracy > 0.95, "{apart:?}");
        assert!(apart.log_loss < 0.2, "{apart:?}");
        let same = c2st(&smooth[..30], &smooth[30..], &cfg);
        assert!(same.accuracy < 0.75, "{same:?}");
        assert!(same.log_loss > 0.5, "{same:?}");
        assert_eq!(same.per_set, 30);
        // The distance is 0 for a set against itself and orders the sets the same way.
        assert!(frechet_distance(&smooth, &smooth, &smooth).abs() < 1e-6);
        let near = frechet_distance(&smooth[..30], &smooth[30..], &smooth);
        let far = frechet_distance(&noisy, &smooth, &smooth);
        assert!(far > 10.0 * near, "{far} {near}");
    }

    #[test]
    fn blur_keeps_drops_and_averages_returns_only() {
        let x = vec![0.0, -1.0, 0.5, 0.1, 0.2, 0.3];
        let b = blur_returns(&x, 2, 3);
        assert_eq!(b[1], -1.0);
        // Pixel (0,0) sees (0,0), (0,2), (1,0), (1,1), (1,2) among returns (circular columns).
        assert!((b[0] - (0.0 + 0.5 + 0.1 + 0.2 + 0.3) / 5.0).abs() < 1e-6);
    }

    #[test]
    fn features_have_a_fixed_length_and_see_drop_clusters() {
        let (h, w) = (8, 32);
        let salt: Vec<f32> = (0..h * w)
            .map(|k| if k % 7 == 0 { -1.0 } else { 0.0 })
            .collect();
        let block: Vec<f32> = (0..h * w)
            .map(|k| if k % w < 5 { -1.0 } else { 0.0 })
            .collect();
        let (fs, fb) = (
            texture_features(&salt, h, w),
            texture_features(&block, h, w),
        );
        assert_eq!(fs.len(), fb.len());
        let isolated = fs.len() - 4;
        assert!(
            fs[isolated] > 0.9 && fb[isolated] == 0.0,
            "{} {}",
            fs[isolated],
            fb[isolated]
        );
    }
}
