//! Range-residual effects of the diagnosis: effects that move returns
//! instead of dropping them. Unpaired scenes have no per-pixel truth, so each
//! family looks at a local statistic whose distribution the scene hardly changes,
//! takes the simulated recording's empirical distribution of it as the
//! reference, and fits the effect as a transformation of that reference by
//! maximum likelihood on real training scans, judged on held-out real scans.
//!
//! | family | statistic | model |
//! |---|---|---|
//! | `range_noise` | second difference along a row, `r_k − (r_{k−1} + r_{k+1}) / 2`, off depth edges, by range | reference ⊛ N(0, 1.5 σ(d)²), `σ(d) = sigma0_m + k d` |
//! | `mixed_pixels` | at a step edge along a row (two flat sides > 1.5 m apart): is the pixel strictly between them? | Bernoulli per gap class, `b_sim + (1 − b_sim) a`, `a` ≈ 0.8 × prob |
//! | `motion_distortion` | range step across the scan seam, from the first fired return to the last where they are neighbours (the seam each cloud's firing order shows, else straight ahead), divided by the step a metre of forward motion makes on the surface there, on surfaces that face the motion | the recording's own divided column steps near the seam, a share of them shifted by `m`, the motion per sweep (speed `m / period`) |

use serde_json::{Map, json};

use super::features::ScanFeatures;
use super::stats::erfc;

mod motion;
pub use motion::MotionFamily;

/// Observations of one statistic: (value, covariate), pooled over scans.
pub type Obs = Vec<(f32, f32)>;

/// What a family knows beyond the scans.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ResidualContext {
    /// Ego speed of the real recording, m/s, if known (motion distortion).
    pub speed_mps: Option<f64>,
    /// Sweep period, seconds.
    pub period_s: f64,
    /// Where the real recording's sweeps start, as its clouds' firing order says
    /// ([`crate::lidar::sweep::Seam`]): the seam's azimuth (radians) and whether the sweep
    /// turns counter-clockwise. `None`: KITTI's convention, straight ahead and
    /// counter-clockwise.
    pub sweep: Option<(f32, bool)>,
}

/// One fitted residual effect with its held-out numbers (NLL per observation).
#[derive(Debug, Clone, PartialEq)]
pub struct ResidualFit {
    pub id: &'static str,
    pub before_nll: f64,
    pub after_nll: f64,
    pub penalty: f64,
    pub test_obs: usize,
    pub params: Map<String, serde_json::Value>,
    pub physics: Map<String, serde_json::Value>,
    pub location: String,
}

impl ResidualFit {
    pub fn gain(&self) -> f64 {
        self.before_nll - self.after_nll
    }
    pub fn significant(&self) -> bool {
        self.gain() > self.penalty
    }
}

/// A range-residual candidate.
pub trait ResidualFamily: Sync {
    fn id(&self) -> &'static str;
    /// The statistic's observations in `scans`.
    fn observations(&self, scans: &[ScanFeatures]) -> Obs;
    /// Fits on `train` against the reference `sim`, evaluates on `test`.
    fn fit(&self, sim: &Obs, train: &Obs, test: &Obs, ctx: &ResidualContext)
    -> Option<ResidualFit>;
}

/// All residual candidates.
pub fn families() -> Vec<Box<dyn ResidualFamily>> {
    vec![
        Box::new(RangeNoiseFamily),
        Box::new(MixedPixelsFamily),
        Box::new(MotionFamily),
    ]
}

/// Smallest held-out gain (nats per observation) of a residual effect: the
/// statistics vary with the scene (vegetation, slanted surfaces) more than a
/// drop mask does.
pub const MIN_RESIDUAL_GAIN_NATS: f64 = 5e-3;

fn penalty(n_params: usize, n_train: usize) -> f64 {
    let n = n_train.max(2) as f64;
    (n_params as f64 * n.ln() / (2.0 * n)).max(MIN_RESIDUAL_GAIN_NATS)
}

fn round4(x: f64) -> f64 {
    (x * 1e4).round() / 1e4
}

/// Standard normal CDF.
fn phi(x: f64) -> f64 {
    0.5 * erfc(-x / std::f64::consts::SQRT_2)
}

/// Values binned on `[lo, lo + n h)`; outside counted apart.
#[derive(Debug, Clone, PartialEq)]
struct Hist {
    lo: f64,
    h: f64,
    counts: Vec<f64>,
    outside: f64,
}

impl Hist {
    fn new(lo: f64, h: f64, n: usize) -> Self {
        Hist {
            lo,
            h,
            counts: vec![0.0; n],
            outside: 0.0,
        }
    }
    fn add(&mut self, x: f64) {
        let j = ((x - self.lo) / self.h).floor();
        if j >= 0.0 && (j as usize) < self.counts.len() {
            self.counts[j as usize] += 1.0;
        } else {
            self.outside += 1.0;
        }
    }
    fn total(&self) -> f64 {
        self.counts.iter().sum::<f64>() + self.outside
    }

    /// Total NLL of the observations `obs` (same binning) under this reference
    /// convolved with N(shift, sigma²): probability per bin, outliers uniform.
    fn nll_of(&self, obs: &Hist, sigma: f64, shift: f64) -> f64 {
        self.nll_of_mixture(obs, &[(1.0, &self.probs(sigma, shift))])
    }

    /// Probability of each bin, and of falling outside them, under this reference
    /// convolved with N(shift, sigma²).
    fn probs(&self, sigma: f64, shift: f64) -> BinProbs {
        let n = self.counts.len();
        let total = self.total().max(1.0);
        // Bin-to-bin transfer G[d] for d = j - i in [-(n-1), n-1].
        let s = (sigma * sigma + 0.25 * self.h * self.h).sqrt();
        let g: Vec<f64> = (0..2 * n - 1)
            .map(|t| {
                let d = t as f64 - (n - 1) as f64;
                phi((d * self.h + 0.5 * self.h - shift) / s)
                    - phi((d * self.h - 0.5 * self.h - shift) / s)
            })
            .collect();
        let p_out = (self.outside / total).clamp(1e-3, 0.5);
        let eps = 0.01;
        let bins = (0..n)
            .map(|j| {
                let m: f64 = (self.counts.iter().enumerate())
                    .filter(|(_, r)| **r > 0.0)
                    .map(|(i, r)| r * g[j + n - 1 - i])
                    .sum();
                (1.0 - p_out) * ((1.0 - eps) * m / total + eps / n as f64)
            })
            .collect();
        BinProbs {
            bins,
            outside: p_out,
        }
    }

    /// Total NLL of `obs` under a mixture of binned distributions `(weight, probs)`.
    fn nll_of_mixture(&self, obs: &Hist, parts: &[(f64, &BinProbs)]) -> f64 {
        let p_at = |j: Option<usize>| -> f64 {
            parts
                .iter()
                .map(|(w, p)| w * j.map_or(p.outside, |j| p.bins[j]))
                .sum()
        };
        let inside: f64 = (obs.counts.iter().enumerate())
            .filter(|(_, c)| **c > 0.0)
            .map(|(j, c)| -c * p_at(Some(j)).max(1e-300).ln())
            .sum();
        inside - obs.outside * p_at(None).ln()
    }
}

/// A binned distribution: the probability of each bin and of falling outside them.
struct BinProbs {
    bins: Vec<f64>,
    outside: f64,
}

/// Reference and observation histograms per covariate bin.
struct Binned {
    cov_edges: Vec<f32>,
    refs: Vec<Hist>,
}

impl Binned {
    fn cov_bin(&self, cov: f32) -> usize {
        self.cov_edges.iter().filter(|e| **e <= cov).count().max(1) - 1
    }
    /// Reference per covariate bin; sparse bins borrow the pooled reference.
    fn new(sim: &Obs, cov_edges: Vec<f32>, lo: f64, h: f64, n: usize) -> Self {
        let mut b = Binned {
            cov_edges,
            refs: Vec::new(),
        };
        let mut pooled = Hist::new(lo, h, n);
        let mut per = vec![Hist::new(lo, h, n); b.cov_edges.len()];
        for &(v, c) in sim {
            pooled.add(f64::from(v));
            per[b.cov_bin(c)].add(f64::from(v));
        }
        b.refs = per
            .into_iter()
            .map(|hst| {
                if hst.total() < 200.0 {
                    pooled.clone()
                } else {
                    hst
                }
            })
            .collect();
        b
    }
    fn observe(&self, obs: &Obs) -> Vec<Hist> {
        let mut out: Vec<Hist> = self
            .refs
            .iter()
            .map(|r| Hist::new(r.lo, r.h, r.counts.len()))
            .collect();
        for &(v, c) in obs {
            out[self.cov_bin(c)].add(f64::from(v));
        }
        out
    }
    fn centre(&self, b: usize) -> f64 {
        let lo = f64::from(self.cov_edges[b]);
        let hi = self
            .cov_edges
            .get(b + 1)
            .map_or(lo + 10.0, |x| f64::from(*x));
        0.5 * (lo + hi)
    }
    /// NLL per observation with noise `sigma(cov)` and shift `shift(cov)`.
    fn nll(&self, obs: &[Hist], sigma: impl Fn(f64) -> f64, shift: f64) -> f64 {
        let n: f64 = obs.iter().map(|o| o.total()).sum();
        let total: f64 = self
            .refs
            .iter()
            .zip(obs)
            .enumerate()
            .filter(|(_, (_, o))| o.total() > 0.0)
            .map(|(b, (r, o))| r.nll_of(o, sigma(self.centre(b)), shift))
            .sum();
        total / n.max(1.0)
    }
}

/// Calls `visit(scan, k)` for every return whose left and right neighbours in its row are
/// returns too (the local statistics of range noise and mixed pixels need both).
fn for_each_row_triplet(scans: &[ScanFeatures], mut visit: impl FnMut(&ScanFeatures, usize)) {
    for f in scans {
        let w = f.width;
        for k in 0..f.len() {
            let j = k % w;
            if j > 0 && j + 1 < w && f.kept[k] && f.kept[k - 1] && f.kept[k + 1] && !f.in_gap(k) {
                visit(f, k);
            }
        }
    }
}

/// Smallest range noise that is claimed, as sigma at 50 m: below 1.5 cm it is near real
/// sensors' range quantisation (~1.2 cm) and within what two scenes' surface roughness
/// moves the statistic by (a null pair read 1.0 cm at 50 m as noise).
const MIN_NOISE_AT_50M: f64 = 0.015;

/// `range_noise`: Gaussian range noise growing with range.
pub struct RangeNoiseFamily;

impl ResidualFamily for RangeNoiseFamily {
    fn id(&self) -> &'static str {
        "range_noise"
    }
    fn observations(&self, scans: &[ScanFeatures]) -> Obs {
        let mut obs = Vec::new();
        for_each_row_triplet(scans, |f, k| {
            if f.edge_px[k] >= 2 {
                let r = f.range_m[k];
                obs.push((r - 0.5 * (f.range_m[k - 1] + f.range_m[k + 1]), r));
            }
        });
        obs
    }
    fn fit(&self, sim: &Obs, train: &Obs, test: &Obs, _: &ResidualContext) -> Option<ResidualFit> {
        if sim.len() < 500 || train.len() < 500 || test.len() < 500 {
            return None;
        }
        let edges: Vec<f32> = (0..8).map(|i| 10.0 * i as f32).collect();
        let binned = Binned::new(sim, edges, -0.4, 0.005, 160);
        let (h_train, h_test) = (binned.observe(train), binned.observe(test));
        // e = n_k - (n_{k-1} + n_{k+1}) / 2: variance 1.5 sigma^2.
        let model = |s0: f64, k: f64| move |d: f64| 1.5f64.sqrt() * (s0 + k * d);
        let mut best = (0.0, 0.0, binned.nll(&h_train, model(0.0, 0.0), 0.0));
        for s0 in [0.0, 0.005, 0.01, 0.015, 0.02, 0.03, 0.04, 0.06, 0.08, 0.1] {
            for k in [0.0, 1e-4, 2e-4, 5e-4, 1e-3, 2e-3] {
                if s0 + 50.0 * k < MIN_NOISE_AT_50M {
                    continue;
                }
                let nll = binned.nll(&h_train, model(s0, k), 0.0);
                if nll < best.2 {
                    best = (s0, k, nll);
                }
            }
        }
        let (s0, k, _) = best;
        let mut params = Map::new();
        params.insert("sigma0_m".into(), json!(round4(s0)));
        params.insert("k".into(), json!(round4(k)));
        let mut physics = Map::new();
        physics.insert("range_noise".into(), json!({"sigma0_m": s0, "k": k}));
        Some(ResidualFit {
            id: self.id(),
            before_nll: binned.nll(&h_test, model(0.0, 0.0), 0.0),
            after_nll: binned.nll(&h_test, model(s0, k), 0.0),
            penalty: penalty(2, train.len()),
            test_obs: test.len(),
            params,
            physics,
            location: format!(
                "every range (smooth surfaces): sigma {:.1} cm at 10 m, {:.1} cm at 50 m",
                100.0 * (s0 + 10.0 * k),
                100.0 * (s0 + 50.0 * k)
            ),
        })
    }
}

/// Smallest range gap between a pixel's neighbours that makes it a depth edge.
const MIXED_MIN_GAP_M: f32 = 1.5;
/// Share of a mixed pixel's uniform range that lies strictly between its
/// neighbours (margins of 10 % of the gap on both sides).
const MIXED_INSIDE: f64 = 0.8;
/// Smallest fitted share of mixed edge pixels that is claimed.
const MIN_MIXED_SHARE: f64 = 0.1;
/// A step edge's two sides must each be flat to this share of the gap.
const MIXED_FLAT_SHARE: f32 = 0.15;

/// `mixed_pixels`: returns between the two surfaces of a depth edge.
pub struct MixedPixelsFamily;

impl MixedPixelsFamily {
    /// The step edge through pixel `k` along its row: five kept pixels `a b k c d`
    /// with `a ≈ b` and `c ≈ d` (each side one flat surface) and `b`, `c` more
    /// than the gap apart. Is `k` strictly between the two surfaces? On a
    /// slanted surface (ground, a wall seen obliquely) the steps are even, so it
    /// is no step edge: the statistic does not depend on how much of the scene
    /// is slanted. Columns are left out: beams are far sparser than columns, so
    /// down a column real surfaces (kerbs, car roofs, barriers) lie between the
    /// two sides of an edge as often as mixed pixels do, by scene.
    fn step_edge(f: &ScanFeatures, k: usize) -> Option<(bool, f32)> {
        let j = k % f.width;
        if j < 2 || j + 2 >= f.width {
            return None;
        }
        let idx = [k - 2, k - 1, k, k + 1, k + 2];
        if idx.iter().any(|&i| !f.kept[i]) {
            return None;
        }
        let [a, b, r, c, d] = idx.map(|i| f.range_m[i]);
        let (near, far) = (b.min(c), b.max(c));
        let gap = far - near;
        let flat = MIXED_FLAT_SHARE * gap;
        if gap <= MIXED_MIN_GAP_M || (a - b).abs() > flat || (c - d).abs() > flat {
            return None;
        }
        let margin = 0.1 * gap;
        Some((r > near + margin && r < far - margin, gap))
    }
}

impl ResidualFamily for MixedPixelsFamily {
    fn id(&self) -> &'static str {
        "mixed_pixels"
    }
    fn observations(&self, scans: &[ScanFeatures]) -> Obs {
        let mut obs = Vec::new();
        for f in scans {
            for k in (0..f.len()).filter(|&k| !f.in_gap(k)) {
                if let Some((between, gap)) = Self::step_edge(f, k) {
                    obs.push((f32::from(u8::from(between)), gap));
                }
            }
        }
        obs
    }
    fn fit(&self, sim: &Obs, train: &Obs, test: &Obs, _: &ResidualContext) -> Option<ResidualFit> {
        if sim.len() < 100 || train.len() < 100 || test.len() < 100 {
            return None;
        }
        let rate = |o: &Obs| o.iter().map(|x| f64::from(x.0)).sum::<f64>() / o.len() as f64;
        let reference = EdgeReference::new(sim);
        let a = reference.fit_share(train);
        // Scenes differ in thin objects between edges: a share below
        // MIN_MIXED_SHARE is not attributed to mixed pixels.
        let a = if a < MIN_MIXED_SHARE { 0.0 } else { a };
        let b = rate(sim);
        let p_after = b + (1.0 - b) * a;
        let prob = (a / MIXED_INSIDE).min(1.0);
        let mut params = Map::new();
        params.insert("prob".into(), json!(round4(prob)));
        params.insert("min_gap_m".into(), json!(MIXED_MIN_GAP_M));
        let mut physics = Map::new();
        physics.insert(
            "mixed_pixels".into(),
            json!({"prob": prob, "min_gap_m": MIXED_MIN_GAP_M}),
        );
        Some(ResidualFit {
            id: self.id(),
            before_nll: reference.nll(test, 0.0),
            after_nll: reference.nll(test, a),
            penalty: penalty(1, train.len()),
            test_obs: test.len(),
            params,
            physics,
            location: format!(
                "step edges (> {MIXED_MIN_GAP_M} m between two flat surfaces, along rows): {:.0} % of edge pixels lie between the two surfaces (sim {:.0} %)",
                100.0 * p_after,
                100.0 * b
            ),
        })
    }
}

/// Upper ends of the gap classes of step edges, meters (the last class is open). Wide gaps
/// leave room for thin objects between the two surfaces, so the share of edge pixels that lie
/// between them grows with the gap in any scene; the reference is taken per gap class, so a
/// scene with other gaps than the simulated one is no mixed-pixel evidence.
const MIXED_GAP_CLASSES_M: [f32; 4] = [3.0, 6.0, 12.0, 24.0];

/// The simulated recording's share of between pixels per gap class (Laplace-smoothed).
struct EdgeReference {
    share: Vec<f64>,
}

impl EdgeReference {
    fn class(gap: f32) -> usize {
        MIXED_GAP_CLASSES_M
            .iter()
            .position(|&g| gap < g)
            .unwrap_or(MIXED_GAP_CLASSES_M.len())
    }

    /// (between, all) counts per gap class.
    fn counts(obs: &Obs) -> Vec<(f64, f64)> {
        let mut c = vec![(0.0, 0.0); MIXED_GAP_CLASSES_M.len() + 1];
        for &(between, gap) in obs {
            let k = &mut c[Self::class(gap)];
            k.0 += f64::from(between);
            k.1 += 1.0;
        }
        c
    }

    fn new(sim: &Obs) -> Self {
        let share = Self::counts(sim)
            .into_iter()
            .map(|(k, n)| (k + 0.5) / (n + 1.0))
            .collect();
        Self { share }
    }

    /// NLL per observation when a share `a` of the edge pixels that the reference keeps on
    /// a surface are mixed.
    fn nll(&self, obs: &Obs, a: f64) -> f64 {
        self.nll_of_counts(&Self::counts(obs), a)
    }

    fn nll_of_counts(&self, counts: &[(f64, f64)], a: f64) -> f64 {
        let total: f64 = counts
            .iter()
            .zip(&self.share)
            .map(|(&(k, n), &b)| {
                let p = (b + (1.0 - b) * a).clamp(1e-6, 1.0 - 1e-6);
                -(k * p.ln() + (n - k) * (1.0 - p).ln())
            })
            .sum();
        let n: f64 = counts.iter().map(|c| c.1).sum();
        total / n.max(1.0)
    }

    /// Maximum-likelihood share on `obs`, to 0.005.
    fn fit_share(&self, obs: &Obs) -> f64 {
        let counts = Self::counts(obs);
        (0..=200)
            .map(|i| f64::from(i) / 200.0)
            .map(|a| (a, self.nll_of_counts(&counts, a)))
            .min_by(|x, y| x.1.total_cmp(&y.1))
            .map_or(0.0, |(a, _)| a)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `n` edge observations at `gap` meters, the first `between` of them between the sides.
    fn edges(n: usize, between: usize, gap: f32) -> Obs {
        (0..n)
            .map(|i| (f32::from(u8::from(i < between)), gap))
            .collect()
    }

    /// Second differences of `n` returns at 5-60 m with range noise `sigma(d)` on top of a
    /// scene roughness of 2 mm.
    fn second_differences(n: usize, seed: u64, sigma: impl Fn(f32) -> f32) -> Obs {
        let mut rng = crate::util::rng::Rng::new(seed);
        (0..n)
            .map(|_| {
                let d = 5.0 + 55.0 * rng.uniform();
                let s = (0.002f32.powi(2) + 1.5 * sigma(d).powi(2)).sqrt();
                (s * rng.normal(), d)
            })
            .collect()
    }

    #[test]
    fn range_noise_below_a_centimetre_is_not_claimed_and_real_noise_is() {
        let fit = |sigma: fn(f32) -> f32| {
            let sim = second_differences(20_000, 1, |_| 0.0);
            let train = second_differences(20_000, 2, sigma);
            let test = second_differences(20_000, 3, sigma);
            RangeNoiseFamily
                .fit(&sim, &train, &test, &ResidualContext::default())
                .expect("enough returns")
        };
        // Rougher surfaces in one scene look like a few millimetres of noise (0.5 cm at
        // 50 m): no claim.
        let rough = fit(|d| 1e-4 * d);
        assert!(!rough.significant(), "gain {} claimed", rough.gain());
        let noisy = fit(|d| 0.02 + 2e-4 * d);
        assert!(noisy.significant());
        assert!((noisy.params["sigma0_m"].as_f64().unwrap() - 0.02).abs() < 0.011);
    }

    #[test]
    fn a_scene_with_wider_edges_is_no_mixed_pixel_evidence() {
        // Wide gaps have more thin objects between their sides in both recordings.
        let sim: Obs = [edges(1000, 50, 2.0), edges(1000, 400, 30.0)].concat();
        let real: Obs = [edges(200, 10, 2.0), edges(1800, 720, 30.0)].concat();
        let rate = |o: &Obs| o.iter().map(|x| f64::from(x.0)).sum::<f64>() / o.len() as f64;
        let pooled = (rate(&real) - rate(&sim)) / (1.0 - rate(&sim));
        assert!(
            pooled > MIN_MIXED_SHARE,
            "the pooled share {pooled} would be claimed"
        );
        let reference = EdgeReference::new(&sim);
        assert!(reference.fit_share(&real) < 0.01);
        let fit = MixedPixelsFamily
            .fit(&sim, &real, &real, &ResidualContext::default())
            .expect("enough edges");
        assert!(!fit.significant(), "gain {} named", fit.gain());
    }

    #[test]
    fn mixed_pixels_raise_the_between_share_in_every_gap_class() {
        let sim: Obs = [edges(1000, 50, 2.0), edges(1000, 400, 30.0)].concat();
        // Half of the pixels the reference keeps on a surface are mixed: 0.05 + 0.95 / 2
        // and 0.4 + 0.6 / 2.
        let real: Obs = [edges(600, 315, 2.0), edges(400, 280, 30.0)].concat();
        let reference = EdgeReference::new(&sim);
        assert!((reference.fit_share(&real) - 0.5).abs() < 0.02);
        let fit = MixedPixelsFamily
            .fit(&sim, &real, &real, &ResidualContext::default())
            .expect("enough edges");
        assert!(fit.significant());
        let prob = fit.params["prob"].as_f64().expect("prob");
        assert!((prob - 0.5 / MIXED_INSIDE).abs() < 0.03, "prob {prob}");
    }
}
