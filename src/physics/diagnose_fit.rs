//! Maximum-likelihood fits of candidate drop effects on real-side pixels
//! (issue 6): which left-out physics explains the real ray-drop masks?
//!
//! This module owns, per candidate effect, a histogram of (pixels, dropped) over
//! the effect's feature (completed range, or cos incidence of the completed
//! normals, from [`ScanFeatures`]), and a grid + golden-section maximum-likelihood
//! fit of the effect's parameters using the physics module's own
//! [`Effect::drop_prob`] formula. The baseline is the simulated recording itself:
//! its conditional keep rate per bin `k_sim(x)` carries everything both sides
//! share (no-hit sky, the sensor's range limit, neighbour-fill artefacts), so
//! `keep(x) = c k_sim(x) (1 - p(x))`, with `c` absorbing a global rate offset
//! (the sim's uniform dropout). `before` is the sim as given (`c = 1`, no effect),
//! the null is `c` alone, and an effect is claimed only if its held-out gain over
//! the null beats a penalty for its two extra parameters. Pixels whose feature is
//! unknown (nothing to complete them from) are left out.

use super::diagnose_features::ScanFeatures;
use super::dropout::{IncidenceDropout, RangeDropout};
use super::{Effect, RayFeatures};
use crate::sim::Material;

/// A drop effect the diagnosis can fit.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum Candidate {
    RangeDropout,
    IncidenceDropout,
}

/// Histogram resolution per candidate: range in 0.5 m bins up to 150 m,
/// cos(incidence) in 100 bins.
const RANGE_BIN_M: f32 = 0.5;
const RANGE_BINS: usize = 300;
const COS_BINS: usize = 100;

impl Candidate {
    pub const ALL: [Candidate; 2] = [Candidate::RangeDropout, Candidate::IncidenceDropout];

    /// The catalogue id.
    pub fn id(self) -> &'static str {
        match self {
            Candidate::RangeDropout => "range_dropout",
            Candidate::IncidenceDropout => "incidence_dropout",
        }
    }

    /// Names of the two fitted shape parameters.
    pub fn param_names(self) -> [&'static str; 2] {
        match self {
            Candidate::RangeDropout => ["range_50_m", "softness"],
            Candidate::IncidenceDropout => ["cos_50", "softness"],
        }
    }

    /// The effect with shape parameters `(a, b)`.
    pub fn effect(self, a: f32, b: f32) -> Box<dyn Effect> {
        match self {
            Candidate::RangeDropout => Box::new(RangeDropout {
                enabled: true,
                range_50_m: a,
                softness: b,
            }),
            Candidate::IncidenceDropout => Box::new(IncidenceDropout {
                enabled: true,
                cos_50: a,
                softness: b,
            }),
        }
    }

    /// Search grid for the first shape parameter.
    fn grid_a(self) -> Vec<f32> {
        match self {
            // Geometric 5 m .. 300 m.
            Candidate::RangeDropout => (0..40)
                .map(|i| 5.0 * (60.0f32).powf(i as f32 / 39.0))
                .collect(),
            Candidate::IncidenceDropout => (1..=40).map(|i| 0.6 * i as f32 / 40.0).collect(),
        }
    }

    fn grid_b(self) -> Vec<f32> {
        vec![0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5, 0.7, 1.0]
    }

    /// Histogram bin of pixel `k`, or None where the feature is unknown.
    fn bin(self, f: &ScanFeatures, k: usize) -> Option<usize> {
        match self {
            Candidate::RangeDropout => {
                let r = f.range_m[k];
                r.is_finite()
                    .then(|| ((r.max(0.0) / RANGE_BIN_M) as usize).min(RANGE_BINS - 1))
            }
            Candidate::IncidenceDropout => {
                let c = f.incidence_rad[k].cos();
                c.is_finite()
                    .then(|| ((c.clamp(0.0, 1.0) * COS_BINS as f32) as usize).min(COS_BINS - 1))
            }
        }
    }

    fn bins(self) -> usize {
        match self {
            Candidate::RangeDropout => RANGE_BINS,
            Candidate::IncidenceDropout => COS_BINS,
        }
    }

    /// The ray a histogram bin stands for (its centre).
    fn ray(self, bin: usize) -> RayFeatures {
        let (range_m, incidence_rad) = match self {
            Candidate::RangeDropout => ((bin as f32 + 0.5) * RANGE_BIN_M, 0.0),
            Candidate::IncidenceDropout => (10.0, ((bin as f32 + 0.5) / COS_BINS as f32).acos()),
        };
        RayFeatures {
            row: 0,
            column: 0,
            range_m,
            incidence_rad,
            material: Material::Concrete,
            reflectivity: 0.5,
            intensity: 0.5,
            azimuth_rad: 0.0,
            elevation_rad: 0.0,
        }
    }

    /// (pixels, dropped) per bin over scans, pixels with a completed range above
    /// `reach_m` left out.
    pub fn histogram(self, scans: &[ScanFeatures], reach_m: f32) -> Histogram {
        let mut counts = vec![(0u64, 0u64); self.bins()];
        for f in scans {
            for k in 0..f.len() {
                if f.range_m[k] > reach_m {
                    continue;
                }
                if let Some(b) = self.bin(f, k) {
                    counts[b].0 += 1;
                    counts[b].1 += u64::from(!f.kept[k]);
                }
            }
        }
        Histogram { counts }
    }
}

/// (pixels, dropped) per feature bin.
#[derive(Debug, Clone, PartialEq)]
pub struct Histogram {
    pub counts: Vec<(u64, u64)>,
}

impl Histogram {
    pub fn pixels(&self) -> u64 {
        self.counts.iter().map(|c| c.0).sum()
    }

    pub fn drop_rate(&self) -> f64 {
        let dropped: u64 = self.counts.iter().map(|c| c.1).sum();
        dropped as f64 / self.pixels().max(1) as f64
    }

    /// Mean per-pixel negative log-likelihood when bin `b` drops with `drop_prob[b]`.
    pub fn nll(&self, drop_prob: &[f64]) -> f64 {
        let mut total = 0.0;
        for (&(n, d), &p) in self.counts.iter().zip(drop_prob) {
            let p = p.clamp(1e-9, 1.0 - 1e-9);
            total -= d as f64 * p.ln() + (n - d) as f64 * (1.0 - p).ln();
        }
        total / self.pixels().max(1) as f64
    }
}

/// One candidate's fit and its held-out evaluation.
#[derive(Debug, Clone, PartialEq)]
pub struct EffectFit {
    pub candidate: Candidate,
    /// Fitted (name, value): the two shape parameters, then `keep_scale` (`c`).
    pub params: Vec<(&'static str, f64)>,
    /// Held-out per-pixel NLL of the sim as given (`c = 1`, no effect).
    pub before_nll: f64,
    /// Held-out per-pixel NLL of the null (`c` fitted, no effect).
    pub null_nll: f64,
    /// Held-out per-pixel NLL with the fitted effect.
    pub nll: f64,
    /// Penalty per pixel for the two extra parameters: the BIC term, at least
    /// [`MIN_GAIN_NATS`].
    pub penalty: f64,
    /// Held-out pixels the comparison used.
    pub test_pixels: u64,
}

impl EffectFit {
    /// Held-out NLL gain over the null, nats per pixel.
    pub fn gain(&self) -> f64 {
        self.null_nll - self.nll
    }

    /// Whether the effect beats the null on held-out data after the penalty.
    pub fn significant(&self) -> bool {
        self.gain() > self.penalty
    }
}

/// Errors of a fit.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum FitError {
    #[error("{0}: no pixel with a known feature in the {1} scans; nothing to fit")]
    NoPixels(&'static str, &'static str),
}

/// Sim keep rate per bin, smoothed towards the sim's global keep rate with the
/// weight of [`SMOOTHING_PIXELS`] pixels (bins the sim hardly visits).
fn sim_keep(sim: &Histogram) -> Vec<f64> {
    let global = 1.0 - sim.drop_rate();
    sim.counts
        .iter()
        .map(|&(n, d)| ((n - d) as f64 + SMOOTHING_PIXELS * global) / (n as f64 + SMOOTHING_PIXELS))
        .collect()
}

/// Prior weight (pixels) of the sim's global keep rate in each bin's baseline.
const SMOOTHING_PIXELS: f64 = 20.0;

/// Drop probability per bin: `1 - c k_sim (1 - p)`.
fn drop_probs(keep_sim: &[f64], shape: &[f64], c: f64) -> Vec<f64> {
    keep_sim
        .iter()
        .zip(shape)
        .map(|(k, p)| 1.0 - c * k * (1.0 - p))
        .collect()
}

fn shape_probs(candidate: Candidate, a: f32, b: f32) -> Vec<f64> {
    let effect = candidate.effect(a, b);
    (0..candidate.bins())
        .map(|bin| f64::from(effect.drop_prob(&candidate.ray(bin)).clamp(0.0, 1.0)))
        .collect()
}

/// The keep-rate scale `c` in [0.5, 2] minimising the NLL (golden section).
fn best_scale(hist: &Histogram, keep_sim: &[f64], shape: &[f64]) -> (f64, f64) {
    let f = |c: f64| hist.nll(&drop_probs(keep_sim, shape, c));
    let (mut lo, mut hi) = (0.5f64, 2.0f64);
    let g = (5f64.sqrt() - 1.0) / 2.0;
    for _ in 0..48 {
        let (m1, m2) = (hi - g * (hi - lo), lo + g * (hi - lo));
        if f(m1) <= f(m2) {
            hi = m2;
        } else {
            lo = m1;
        }
    }
    let c = 0.5 * (lo + hi);
    (c, f(c))
}

/// Fits `candidate` on the real `train` scans against the simulated recording
/// `sim`, and evaluates it on the held-out real `test` scans.
pub fn fit_effect(
    candidate: Candidate,
    sim: &[ScanFeatures],
    train: &[ScanFeatures],
    test: &[ScanFeatures],
) -> Result<EffectFit, FitError> {
    let reach_m = reach_m(sim, train);
    let h_sim = candidate.histogram(sim, reach_m);
    let h_train = candidate.histogram(train, reach_m);
    let h_test = candidate.histogram(test, reach_m);
    for (h, which) in [
        (&h_sim, "simulated"),
        (&h_train, "training"),
        (&h_test, "held-out"),
    ] {
        if h.pixels() == 0 {
            return Err(FitError::NoPixels(candidate.id(), which));
        }
    }
    let keep_sim = sim_keep(&h_sim);
    let no_effect = vec![0.0; candidate.bins()];
    let mut best: Option<(f64, f32, f32, f64)> = None;
    for a in candidate.grid_a() {
        for b in candidate.grid_b() {
            let shape = shape_probs(candidate, a, b);
            let (c, nll) = best_scale(&h_train, &keep_sim, &shape);
            if best.is_none_or(|(n, ..)| nll < n) {
                best = Some((nll, a, b, c));
            }
        }
    }
    let Some((_, a, b, c)) = best else {
        return Err(FitError::NoPixels(candidate.id(), "training"));
    };
    let (c_null, _) = best_scale(&h_train, &keep_sim, &no_effect);
    let n = h_train.pixels() as f64;
    let [name_a, name_b] = candidate.param_names();
    Ok(EffectFit {
        candidate,
        params: vec![
            (name_a, f64::from(a)),
            (name_b, f64::from(b)),
            ("keep_scale", c),
        ],
        before_nll: h_test.nll(&drop_probs(&keep_sim, &no_effect, 1.0)),
        null_nll: h_test.nll(&drop_probs(&keep_sim, &no_effect, c_null)),
        nll: h_test.nll(&drop_probs(&keep_sim, &shape_probs(candidate, a, b), c)),
        penalty: (2.0 * n.ln() / (2.0 * n)).max(MIN_GAIN_NATS),
        test_pixels: h_test.pixels(),
    })
}

/// Pixels completed to near the sensor's reach are ambiguous: "no surface within
/// reach" (scene) or "dropped" (physics); their share depends on the scene, so
/// the fit leaves out completed ranges above `REACH_FRACTION` times the
/// `REACH_QUANTILE` quantile of kept ranges (the smaller of the two sides).
pub const REACH_QUANTILE: f64 = 0.995;
pub const REACH_FRACTION: f32 = 0.85;

/// The range beyond which completed pixels are left out: [`REACH_FRACTION`] of
/// the smaller of the two sides' [`REACH_QUANTILE`] kept-range quantiles.
pub fn reach_m(sim: &[ScanFeatures], real: &[ScanFeatures]) -> f32 {
    REACH_FRACTION
        * kept_range_quantile(sim, REACH_QUANTILE).min(kept_range_quantile(real, REACH_QUANTILE))
}

/// The `q` quantile of kept ranges over scans (infinity when none is kept).
pub fn kept_range_quantile(scans: &[ScanFeatures], q: f64) -> f32 {
    let mut ranges: Vec<f32> = scans
        .iter()
        .flat_map(|f| (0..f.len()).filter(|&k| f.kept[k]).map(|k| f.range_m[k]))
        .filter(|r| r.is_finite())
        .collect();
    if ranges.is_empty() {
        return f32::INFINITY;
    }
    let i = ((ranges.len() - 1) as f64 * q.clamp(0.0, 1.0)) as usize;
    *ranges.select_nth_unstable_by(i, f32::total_cmp).1
}

/// Smallest held-out gain (nats per pixel) an effect must show: pixels of a scan
/// are correlated, so the BIC term alone (which assumes independence) is too lax.
pub const MIN_GAIN_NATS: f64 = 1e-3;

/// Fits every candidate; significant ones first, by held-out gain.
pub fn rank_effects(
    sim: &[ScanFeatures],
    train: &[ScanFeatures],
    test: &[ScanFeatures],
) -> Result<Vec<EffectFit>, FitError> {
    let mut fits = Candidate::ALL
        .iter()
        .map(|&c| fit_effect(c, sim, train, test))
        .collect::<Result<Vec<_>, _>>()?;
    fits.sort_by(|x, y| {
        y.significant()
            .cmp(&x.significant())
            .then(y.gain().total_cmp(&x.gain()))
    });
    Ok(fits)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::physics::dropout::UniformDropout;

    use crate::physics::diagnose_features::simulated_recording as recording;

    fn drop_rate(scans: &[ScanFeatures]) -> f64 {
        scans.iter().map(|s| s.drop_rate()).sum::<f64>() / scans.len() as f64
    }

    /// Real side with `effect`; sim side (other scene) with uniform dropout raised
    /// until the global drop rates match. Returns (sim, real) feature sets.
    fn concealed(effect: Box<dyn Effect>) -> (Vec<ScanFeatures>, Vec<ScanFeatures>) {
        let real = recording(101, 8, vec![effect]);
        let ideal_sim = recording(202, 8, vec![]);
        let (r, s0) = (drop_rate(&real), drop_rate(&ideal_sim));
        assert!(r > s0, "the effect drops rays: real {r} vs ideal sim {s0}");
        let prob = ((r - s0) / (1.0 - s0)) as f32;
        let sim = recording(
            202,
            8,
            vec![Box::new(UniformDropout {
                enabled: true,
                prob,
            })],
        );
        assert!(
            (drop_rate(&sim) - r).abs() < 0.01,
            "concealed: {} vs {r}",
            drop_rate(&sim)
        );
        (sim, real)
    }

    fn split(scans: &[ScanFeatures]) -> (Vec<ScanFeatures>, Vec<ScanFeatures>) {
        let (mut train, mut test) = (Vec::new(), Vec::new());
        for (i, s) in scans.iter().enumerate() {
            if i % 2 == 0 { &mut train } else { &mut test }.push(s.clone());
        }
        (train, test)
    }

    #[test]
    fn histogram_nll_of_the_true_rate_is_the_binary_entropy() {
        let h = Histogram {
            counts: vec![(100, 25), (100, 25)],
        };
        let p = 0.25f64;
        let entropy = -(p * p.ln() + (1.0 - p) * (1.0 - p).ln());
        assert!((h.nll(&[0.25, 0.25]) - entropy).abs() < 1e-12);
        assert!(h.nll(&[0.5, 0.5]) > entropy);
    }

    #[test]
    fn concealed_range_dropout_is_named_and_fitted() {
        // Parameters drawn from a fixed seed across a plausible sensor range.
        for case in 0..3u64 {
            let u = |salt: u64| crate::sim::rng::uniform(&[0xd1a9, case, salt]);
            let truth = (30.0 + 40.0 * u(1), 0.2 + 0.4 * u(2));
            let (sim, real) = concealed(Candidate::RangeDropout.effect(truth.0, truth.1));
            let (train, test) = split(&real);
            let fits = rank_effects(&sim, &train, &test).expect("fits");
            let top = &fits[0];
            assert_eq!(
                top.candidate,
                Candidate::RangeDropout,
                "{truth:?}: {fits:#?}"
            );
            assert!(top.significant(), "{truth:?}: {top:?}");
            let range_50 = top.params[0].1;
            assert!(
                (range_50 / f64::from(truth.0)).ln().abs() < 0.35,
                "range_50_m {range_50} vs {truth:?}"
            );
            assert!(top.nll < top.before_nll, "{top:?}");
            assert!(!fits[1].significant() || fits[1].gain() < top.gain());
        }
    }

    #[test]
    fn same_physics_claims_no_effect() {
        let uniform = || -> Box<dyn Effect> {
            Box::new(UniformDropout {
                enabled: true,
                prob: 0.1,
            })
        };
        for (sim_seed, real_seed) in [(404, 303), (7, 8), (21, 12)] {
            let sim = recording(sim_seed, 8, vec![uniform()]);
            let real = recording(real_seed, 8, vec![uniform()]);
            let (train, test) = split(&real);
            let fits = rank_effects(&sim, &train, &test).expect("fits");
            for fit in &fits {
                assert!(!fit.significant(), "false alarm: {fit:?}");
            }
        }
    }

    #[test]
    fn no_pixels_is_an_error_not_a_panic() {
        assert_eq!(
            fit_effect(Candidate::RangeDropout, &[], &[], &[]),
            Err(FitError::NoPixels("range_dropout", "simulated"))
        );
    }
}
