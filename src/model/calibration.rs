//! Post-hoc calibration of the ray-drop probability x_n (Platt scaling per beam).
//!
//! The generator's keep logit l (x_n = 1 - sigmoid(l)) becomes a(φ) l + b(φ): one (a, b) per
//! beam of the model grid, fitted by logistic regression on decoded training scans against
//! their actual drops, and linearly interpolated in elevation φ for other grids. It travels
//! with the weights (`calibration.json` beside `g_ema.bpk`), because it belongs to the
//! generator (and to the decode that produced the logits it was fitted on).

use anyhow::{Context, Result, bail};
use serde::{Deserialize, Serialize};

/// Per-beam affine maps of the keep logit.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RaydropCalibration {
    /// One entry per beam, sorted by elevation (ascending).
    pub beams: Vec<BeamCalibration>,
    /// How it was fitted (decode, scans, weights), for reports.
    pub fitted_on: String,
}

/// The map of one beam: keep logit -> `scale * logit + bias`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct BeamCalibration {
    pub elevation_rad: f32,
    pub scale: f32,
    pub bias: f32,
}

/// Fitting data of one beam: the decoded keep logits and whether the ray actually returned.
#[derive(Debug, Clone, Default)]
pub struct BeamSamples {
    pub elevation_rad: f32,
    pub logits: Vec<f32>,
    pub kept: Vec<bool>,
}

impl BeamSamples {
    /// Mean negative log-likelihood of the drops under `keep = sigmoid(scale * l + bias)`.
    pub fn nll(&self, scale: f32, bias: f32) -> f64 {
        let n = self.logits.len().max(1) as f64;
        self.logits
            .iter()
            .zip(&self.kept)
            .map(|(l, k)| bernoulli_nll(f64::from(scale * l + bias), *k))
            .sum::<f64>()
            / n
    }
}

/// -log p(kept) for a keep logit `z`, stable for large |z|.
pub fn bernoulli_nll(z: f64, kept: bool) -> f64 {
    // -log sigmoid(z) = softplus(-z); -log(1 - sigmoid(z)) = softplus(z)
    let softplus = |x: f64| x.max(0.0) + (-x.abs()).exp().ln_1p();
    if kept { softplus(-z) } else { softplus(z) }
}

impl RaydropCalibration {
    /// Fit one map per beam (beams without samples are skipped).
    pub fn fit(samples: &[BeamSamples], fitted_on: String) -> Result<Self> {
        let mut beams: Vec<BeamCalibration> = samples
            .iter()
            .filter(|s| !s.logits.is_empty())
            .map(|s| {
                let (scale, bias) = logistic_fit(&s.logits, &s.kept);
                BeamCalibration {
                    elevation_rad: s.elevation_rad,
                    scale,
                    bias,
                }
            })
            .collect();
        if beams.is_empty() {
            bail!("no samples to fit the ray-drop calibration on");
        }
        beams.sort_by(|a, b| a.elevation_rad.total_cmp(&b.elevation_rad));
        Ok(Self { beams, fitted_on })
    }

    /// (scale, bias) at an elevation: linear between the two nearest beams, the end beam's
    /// beyond the ends.
    pub fn params(&self, elevation_rad: f32) -> (f32, f32) {
        let b = &self.beams;
        let i = b.partition_point(|c| c.elevation_rad < elevation_rad);
        if i == 0 {
            return (b[0].scale, b[0].bias);
        }
        if i == b.len() {
            let last = b[b.len() - 1];
            return (last.scale, last.bias);
        }
        let (lo, hi) = (b[i - 1], b[i]);
        let span = hi.elevation_rad - lo.elevation_rad;
        let t = if span > 0.0 {
            (elevation_rad - lo.elevation_rad) / span
        } else {
            0.0
        };
        (
            lo.scale + t * (hi.scale - lo.scale),
            lo.bias + t * (hi.bias - lo.bias),
        )
    }

    /// The calibrated keep logit of a pixel looking at `elevation_rad`.
    pub fn keep_logit(&self, logit: f32, elevation_rad: f32) -> f32 {
        let (a, b) = self.params(elevation_rad);
        a * logit + b
    }

    pub fn from_json(text: &str, source: &str) -> Result<Self> {
        let c: Self = serde_json::from_str(text)
            .with_context(|| format!("'{source}' is not a ray-drop calibration"))?;
        if c.beams.is_empty() {
            bail!("'{source}' has no beams");
        }
        Ok(c)
    }
}

/// Logistic regression of `kept` on [logit, 1] by Newton's method, with a weak ridge towards
/// the identity map (1, 0) so that a beam that always (or never) returns stays finite.
fn logistic_fit(logits: &[f32], kept: &[bool]) -> (f32, f32) {
    const RIDGE: f64 = 1.0;
    let (mut a, mut b) = (1.0f64, 0.0f64);
    for _ in 0..50 {
        let (mut ga, mut gb) = (RIDGE * (a - 1.0), RIDGE * b);
        let (mut haa, mut hab, mut hbb) = (RIDGE, 0.0, RIDGE);
        for (l, k) in logits.iter().zip(kept) {
            let x = f64::from(*l);
            let p = 1.0 / (1.0 + (-(a * x + b)).exp());
            let r = p - f64::from(u8::from(*k));
            ga += r * x;
            gb += r;
            let w = (p * (1.0 - p)).max(1e-12);
            haa += w * x * x;
            hab += w * x;
            hbb += w;
        }
        let det = haa * hbb - hab * hab;
        if det.abs() < 1e-18 {
            break;
        }
        let da = (hbb * ga - hab * gb) / det;
        let db = (haa * gb - hab * ga) / det;
        // Capped: far from the optimum a full Newton step on saturated logits can overshoot.
        let norm = (da * da + db * db).sqrt();
        let step = if norm > 4.0 { 4.0 / norm } else { 1.0 };
        a -= step * da;
        b -= step * db;
        if da.abs() + db.abs() < 1e-7 {
            break;
        }
    }
    (a as f32, b as f32)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::rng::Rng;

    fn samples(elevation_rad: f32, scale: f32, bias: f32, n: usize, seed: u64) -> BeamSamples {
        let mut rng = Rng::new(seed);
        let mut s = BeamSamples {
            elevation_rad,
            ..Default::default()
        };
        for _ in 0..n {
            let l = rng.uniform() * 8.0 - 2.0;
            let p = 1.0 / (1.0 + (-(scale * l + bias)).exp());
            s.logits.push(l);
            s.kept.push(rng.uniform() < p);
        }
        s
    }

    #[test]
    fn fit_recovers_the_map_that_generated_the_drops() {
        let beams = [
            samples(-0.3, 0.5, -1.0, 40_000, 1),
            samples(0.0, 2.0, 0.5, 40_000, 2),
        ];
        let c = RaydropCalibration::fit(&beams, "test".into()).unwrap();
        assert_eq!(c.beams.len(), 2);
        let (a0, b0) = (c.beams[0].scale, c.beams[0].bias);
        let (a1, b1) = (c.beams[1].scale, c.beams[1].bias);
        assert!((a0 - 0.5).abs() < 0.05 && (b0 + 1.0).abs() < 0.08, "{a0} {b0}");
        assert!((a1 - 2.0).abs() < 0.15 && (b1 - 0.5).abs() < 0.15, "{a1} {b1}");
        // the fit is never worse than the identity map on its own data
        for (s, cal) in beams.iter().zip(&c.beams) {
            assert!(s.nll(cal.scale, cal.bias) < s.nll(1.0, 0.0));
        }
    }

    #[test]
    fn a_beam_that_always_returns_gets_a_finite_confident_map() {
        let mut s = samples(0.1, 1.0, 0.0, 2000, 3);
        s.kept.iter_mut().for_each(|k| *k = true);
        let c = RaydropCalibration::fit(&[s.clone()], "test".into()).unwrap();
        let (a, b) = (c.beams[0].scale, c.beams[0].bias);
        assert!(a.is_finite() && b.is_finite());
        // nearly every sample now gets keep > 0.99
        let confident = s
            .logits
            .iter()
            .filter(|l| c.keep_logit(**l, 0.1) > 4.6)
            .count();
        assert!(confident as f32 > 0.95 * s.logits.len() as f32, "{a} {b}");
    }

    #[test]
    fn params_interpolate_in_elevation_and_clamp_at_the_ends() {
        let c = RaydropCalibration {
            beams: vec![
                BeamCalibration {
                    elevation_rad: -0.2,
                    scale: 1.0,
                    bias: 0.0,
                },
                BeamCalibration {
                    elevation_rad: 0.0,
                    scale: 3.0,
                    bias: -2.0,
                },
            ],
            fitted_on: String::new(),
        };
        assert_eq!(c.params(-0.5), (1.0, 0.0));
        assert_eq!(c.params(0.3), (3.0, -2.0));
        let (a, b) = c.params(-0.1);
        assert!((a - 2.0).abs() < 1e-6 && (b + 1.0).abs() < 1e-6);
        assert!((c.keep_logit(2.0, -0.1) - 3.0).abs() < 1e-5);
        let json = serde_json::to_string(&c).unwrap();
        assert_eq!(RaydropCalibration::from_json(&json, "x").unwrap(), c);
        assert!(RaydropCalibration::from_json("{\"beams\":[],\"fitted_on\":\"\"}", "x").is_err());
    }

    #[test]
    fn nll_is_stable_for_saturated_logits() {
        assert!((bernoulli_nll(50.0, true)).abs() < 1e-12);
        assert!((bernoulli_nll(50.0, false) - 50.0).abs() < 1e-9);
        assert!((bernoulli_nll(0.0, true) - std::f64::consts::LN_2).abs() < 1e-12);
    }
}
