//! Post-hoc calibration of the ray-drop probability x_n (Platt scaling per beam).
//!
//! The generator's keep logit l (x_n = 1 - sigmoid(l)) becomes
//! a(φ) l + b(φ) + c(φ) ln(d / 10 m) + e(φ) g, with d the completed depth x_d and g its depth
//! edge strength ([`edge_strength`](crate::lidar::edges::edge_strength)): one (a, b, c, e) per beam of the model grid, fitted by
//! logistic regression on decoded training scans against their actual drops, and linearly
//! interpolated in elevation φ for other grids. The depth and edge terms let the calibration
//! use what the decoded scene says about range (far surfaces and open sky drop more) and about
//! depth edges (a beam split between two surfaces often returns nothing). It travels
//! with the weights (`calibration.json` beside `g_ema.bpk`), because it belongs to the
//! generator (and to the decode that produced the logits it was fitted on).

use anyhow::{Context, Result, bail};
use serde::{Deserialize, Serialize};

use crate::util::math::softplus;

/// Per-beam affine maps of the keep logit.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RaydropCalibration {
    /// One entry per beam, sorted by elevation (ascending).
    pub beams: Vec<BeamCalibration>,
    /// How it was fitted (decode, scans, weights), for reports.
    pub fitted_on: String,
}

/// The map of one beam: keep logit ->
/// `scale * logit + bias + depth_slope * ln(depth / 10 m) + edge_slope * edge`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct BeamCalibration {
    pub elevation_rad: f32,
    pub scale: f32,
    pub bias: f32,
    #[serde(default)]
    pub depth_slope: f32,
    #[serde(default)]
    pub edge_slope: f32,
}

impl BeamCalibration {
    /// No change: the generator's own x_n.
    pub const IDENTITY: BeamCalibration = BeamCalibration {
        elevation_rad: 0.0,
        scale: 1.0,
        bias: 0.0,
        depth_slope: 0.0,
        edge_slope: 0.0,
    };

    fn apply(&self, logit: f32, depth_m: f32, edge: f32) -> f32 {
        self.scale * logit
            + self.bias
            + self.depth_slope * depth_feature(depth_m)
            + self.edge_slope * edge
    }
}

fn depth_feature(depth_m: f32) -> f32 {
    (depth_m.max(0.1) / 10.0).ln()
}

/// Fitting data of one beam: the decoded keep logits and depths, and whether the ray
/// actually returned.
#[derive(Debug, Clone, Default)]
pub struct BeamSamples {
    pub elevation_rad: f32,
    pub logits: Vec<f32>,
    pub depth_m: Vec<f32>,
    /// [`edge_strength`](crate::lidar::edges::edge_strength) of the decoded depth.
    pub edge: Vec<f32>,
    pub kept: Vec<bool>,
}

impl BeamSamples {
    /// Mean negative log-likelihood of the drops under a beam's map.
    pub fn nll(&self, map: &BeamCalibration) -> f64 {
        let n = self.logits.len().max(1) as f64;
        (0..self.logits.len())
            .map(|i| {
                let z = map.apply(self.logits[i], self.depth_m[i], self.edge[i]);
                bernoulli_nll(f64::from(z), self.kept[i])
            })
            .sum::<f64>()
            / n
    }
}

/// -log p(kept) for a keep logit `z`, stable for large |z|.
pub fn bernoulli_nll(z: f64, kept: bool) -> f64 {
    // -log sigmoid(z) = softplus(-z); -log(1 - sigmoid(z)) = softplus(z)
    if kept { softplus(-z) } else { softplus(z) }
}

impl RaydropCalibration {
    /// Fit one map per beam (beams without samples are skipped).
    pub fn fit(samples: &[BeamSamples], fitted_on: String) -> Result<Self> {
        let mut beams: Vec<BeamCalibration> = samples
            .iter()
            .filter(|s| !s.logits.is_empty())
            .map(|s| BeamCalibration {
                elevation_rad: s.elevation_rad,
                ..logistic_fit(s)
            })
            .collect();
        if beams.is_empty() {
            bail!("no samples to fit the ray-drop calibration on");
        }
        beams.sort_by(|a, b| a.elevation_rad.total_cmp(&b.elevation_rad));
        Ok(Self { beams, fitted_on })
    }

    /// The map at an elevation: linear between the two nearest beams, the end beam's beyond
    /// the ends.
    pub fn params(&self, elevation_rad: f32) -> BeamCalibration {
        let b = &self.beams;
        let i = b.partition_point(|c| c.elevation_rad < elevation_rad);
        if i == 0 {
            return b[0];
        }
        if i == b.len() {
            return b[b.len() - 1];
        }
        let (lo, hi) = (b[i - 1], b[i]);
        let span = hi.elevation_rad - lo.elevation_rad;
        let t = if span > 0.0 {
            (elevation_rad - lo.elevation_rad) / span
        } else {
            0.0
        };
        let lerp = |a: f32, b: f32| a + t * (b - a);
        BeamCalibration {
            elevation_rad,
            scale: lerp(lo.scale, hi.scale),
            bias: lerp(lo.bias, hi.bias),
            depth_slope: lerp(lo.depth_slope, hi.depth_slope),
            edge_slope: lerp(lo.edge_slope, hi.edge_slope),
        }
    }

    /// The calibrated keep logit of a pixel looking at `elevation_rad` with completed depth
    /// `depth_m` and depth edge strength `edge` ([`edge_strength`](crate::lidar::edges::edge_strength)).
    pub fn keep_logit(&self, logit: f32, depth_m: f32, edge: f32, elevation_rad: f32) -> f32 {
        self.params(elevation_rad).apply(logit, depth_m, edge)
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

/// Logistic regression of `kept` on [logit, 1, ln(depth / 10 m), edge] by Newton's method, with a
/// weak ridge towards the identity map so that a beam that always (or never) returns stays
/// finite.
fn logistic_fit(s: &BeamSamples) -> BeamCalibration {
    use nalgebra::{Matrix4, Vector4};
    const RIDGE: f64 = 1.0;
    let prior = Vector4::new(1.0, 0.0, 0.0, 0.0);
    let features = |i: usize| {
        Vector4::new(
            f64::from(s.logits[i]),
            1.0,
            f64::from(depth_feature(s.depth_m[i])),
            f64::from(s.edge[i]),
        )
    };
    let objective = |theta: &Vector4<f64>| {
        (0..s.logits.len())
            .map(|i| bernoulli_nll(theta.dot(&features(i)), s.kept[i]))
            .sum::<f64>()
            + 0.5 * RIDGE * (theta - prior).norm_squared()
    };
    let mut theta = prior;
    let mut current = objective(&theta);
    for _ in 0..100 {
        let mut grad = RIDGE * (theta - prior);
        let mut hess = Matrix4::identity() * RIDGE;
        for i in 0..s.logits.len() {
            let x = features(i);
            let p = 1.0 / (1.0 + (-theta.dot(&x)).exp());
            grad += (p - f64::from(u8::from(s.kept[i]))) * x;
            hess += (p * (1.0 - p)).max(1e-12) * x * x.transpose();
        }
        let Some(delta) = hess.cholesky().map(|c| c.solve(&grad)) else {
            break;
        };
        // Backtracking: a full Newton step on saturated logits can overshoot and oscillate.
        let mut t = 1.0;
        let accepted = loop {
            let next = theta - t * delta;
            let value = objective(&next);
            if value <= current {
                break Some((next, value));
            }
            t *= 0.5;
            if t < 1e-6 {
                break None;
            }
        };
        let Some((next, value)) = accepted else { break };
        let converged = current - value < 1e-9 * current.max(1.0);
        theta = next;
        current = value;
        if converged {
            break;
        }
    }
    BeamCalibration {
        elevation_rad: s.elevation_rad,
        scale: theta[0] as f32,
        bias: theta[1] as f32,
        depth_slope: theta[2] as f32,
        edge_slope: theta[3] as f32,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::util::rng::Rng;

    fn samples(map: BeamCalibration, n: usize, seed: u64) -> BeamSamples {
        let mut rng = Rng::new(seed);
        let mut s = BeamSamples {
            elevation_rad: map.elevation_rad,
            ..Default::default()
        };
        for _ in 0..n {
            let l = rng.uniform() * 8.0 - 2.0;
            let d = 2.0 + rng.uniform() * 70.0;
            let g = if rng.uniform() < 0.2 {
                rng.uniform()
            } else {
                0.0
            };
            let p = 1.0 / (1.0 + (-map.apply(l, d, g)).exp());
            s.logits.push(l);
            s.depth_m.push(d);
            s.edge.push(g);
            s.kept.push(rng.uniform() < p);
        }
        s
    }

    fn map(elevation_rad: f32, scale: f32, bias: f32, depth_slope: f32) -> BeamCalibration {
        BeamCalibration {
            elevation_rad,
            scale,
            bias,
            depth_slope,
            edge_slope: 0.0,
        }
    }

    #[test]
    fn fit_recovers_the_map_that_generated_the_drops() {
        let edgy = BeamCalibration {
            edge_slope: -3.0,
            ..map(0.0, 2.0, 0.5, 0.0)
        };
        let truth = [map(-0.3, 0.5, -1.0, -1.5), edgy];
        let beams = [samples(truth[0], 40_000, 1), samples(truth[1], 40_000, 2)];
        let c = RaydropCalibration::fit(&beams, "test".into()).unwrap();
        assert_eq!(c.beams.len(), 2);
        for (fit, t) in c.beams.iter().zip(&truth) {
            let close = (fit.scale - t.scale).abs() < 0.1 * t.scale
                && (fit.bias - t.bias).abs() < 0.15
                && (fit.depth_slope - t.depth_slope).abs() < 0.15
                && (fit.edge_slope - t.edge_slope).abs() < 0.3;
            assert!(close, "fitted {fit:?}, truth {t:?}");
        }
        // the fit is never worse than the identity map on its own data
        for (s, fit) in beams.iter().zip(&c.beams) {
            assert!(s.nll(fit) < s.nll(&BeamCalibration::IDENTITY));
        }
    }

    #[test]
    fn a_beam_that_always_returns_gets_a_finite_confident_map() {
        let mut s = samples(map(0.1, 1.0, 0.0, 0.0), 2000, 3);
        s.kept.iter_mut().for_each(|k| *k = true);
        let c = RaydropCalibration::fit(&[s.clone()], "test".into()).unwrap();
        let fit = c.beams[0];
        assert!(fit.scale.is_finite() && fit.bias.is_finite() && fit.depth_slope.is_finite());
        // the calibrated keep probability is near 1 on average (the ridge keeps it below)
        let mean_keep = (0..s.logits.len())
            .map(|i| 1.0 / (1.0 + (-c.keep_logit(s.logits[i], s.depth_m[i], s.edge[i], 0.1)).exp()))
            .sum::<f32>()
            / s.logits.len() as f32;
        assert!(mean_keep > 0.98, "{fit:?}: mean keep {mean_keep}");
    }

    #[test]
    fn params_interpolate_in_elevation_and_clamp_at_the_ends() {
        let c = RaydropCalibration {
            beams: vec![map(-0.2, 1.0, 0.0, 0.0), map(0.0, 3.0, -2.0, 1.0)],
            fitted_on: String::new(),
        };
        assert_eq!(c.params(-0.5), c.beams[0]);
        assert_eq!(c.params(0.3), c.beams[1]);
        let mid = c.params(-0.1);
        assert!((mid.scale - 2.0).abs() < 1e-6 && (mid.bias + 1.0).abs() < 1e-6);
        assert!((mid.depth_slope - 0.5).abs() < 1e-6);
        // at 10 m the depth term vanishes: 2 * 2 - 1
        assert!((c.keep_logit(2.0, 10.0, 0.0, -0.1) - 3.0).abs() < 1e-5);
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
