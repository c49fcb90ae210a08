//! `motion_distortion`: no de-skew, so a sweep's last returns meet its first at the scan seam
//! a range step apart wherever the surface there faces the motion. A ray fired `t` into the
//! sweep leaves from `v t` farther along, and meets a surface of normal `n` at
//! `r - n . v t / n . d` ([`crate::physics::perturb::moved_range`]): the ground under the
//! sensor is met at the same range, a wall ahead a sweep's motion nearer. So each step across
//! the seam is the scene's own step plus `m g`, with `m` the motion per sweep (m) and
//! `g = -n_x / n . d` the step a metre of forward motion makes on that surface. Steps are
//! read divided by `g`, on surfaces where `g` is large, so every one of them measures `m`
//! directly whatever the seam's azimuth, the ground's share of the seam or the speed; the
//! recording's own steps beside the seam, divided the same way, are the reference.

use serde_json::{Map, json};

use super::{BinProbs, Hist, Obs, ResidualContext, ResidualFamily, ResidualFit, penalty, round4};
use crate::diagnose::features::ScanFeatures;
use crate::lidar::sweep::Seam;

/// Columns either side of the seam whose steps form the motion reference.
const SEAM_CONTROL_COLUMNS: usize = 6;

/// Motion per sweep tried: -1.0 to 4.0 m in 5 cm steps (40 m/s at 10 Hz). Backward a little,
/// as at a standstill; a sensor mounted facing backwards reads as forward motion of the
/// other sign, which the fit does not try.
const SHIFTS: usize = 101;

/// The `i`-th motion per sweep tried, meters.
fn seam_shift(i: usize) -> f64 {
    0.05 * (i as f64 - 20.0)
}

/// Smallest |g| of a step that is read: the step a metre of forward motion makes on its
/// surface, `-n_x / n . d` (1 on a wall met head-on straight ahead or behind, 0 on the ground
/// and on walls along the road). Below it a step says more about the scene than the motion.
const MIN_MOTION_GAIN: f32 = 0.5;
/// Smallest |n . d| of a surface read: nearer edge-on, its normal is too uncertain to divide
/// by.
const MIN_FACING: f32 = 0.3;

/// The step a metre of forward (+x) motion per sweep makes on a return with unit normal `n`
/// and direction `d` (both in the sensor frame); `None` where the surface does not face the
/// motion enough to measure it.
fn motion_gain(n: [f32; 3], d: [f32; 3]) -> Option<f32> {
    let n_dot_d = n[0] * d[0] + n[1] * d[1] + n[2] * d[2];
    if n_dot_d.abs() < MIN_FACING {
        return None;
    }
    let g = -n[0] / n_dot_d;
    (g.abs() >= MIN_MOTION_GAIN).then_some(g)
}

/// Seam steps (divided by their gain) as a mixture: a share of them moved by the motion per
/// sweep, the rest distributed as the steps beside the seam.
struct SeamModel {
    reference: Hist,
    still: BinProbs,
    moved: Vec<BinProbs>,
}

impl SeamModel {
    fn hist(steps: &Obs) -> Hist {
        let mut h = Hist::new(-8.0, 0.05, 320);
        steps.iter().for_each(|&(v, _)| h.add(f64::from(v)));
        h
    }
    fn new(reference: &Obs) -> Self {
        let reference = Self::hist(reference);
        SeamModel {
            still: reference.probs(0.0, 0.0),
            moved: (0..SHIFTS)
                .map(|i| reference.probs(0.0, seam_shift(i)))
                .collect(),
            reference,
        }
    }
    /// NLL per seam step with `share` of them moved by `seam_shift(i)`.
    fn nll(&self, h: &Hist, share: f64, i: usize) -> f64 {
        let parts = [(1.0 - share, &self.still), (share, &self.moved[i])];
        self.reference.nll_of_mixture(h, &parts) / h.total().max(1.0)
    }
    /// Whether at least two thirds of the scans of `by_scan` (their seam steps, each with
    /// [`MIN_SCAN_SEAM_STEPS`] or more) fit `after` (share, shift index) better than
    /// `before`. Motion moves the seam of every scan; an edge of the scene that happens to
    /// lie at the seam of a few scans (its rows all step at once) does not.
    fn most_scans_fit_better(
        &self,
        by_scan: &[Obs],
        before: (f64, usize),
        after: (f64, usize),
    ) -> bool {
        let gains: Vec<f64> = (by_scan.iter())
            .filter(|steps| steps.len() >= MIN_SCAN_SEAM_STEPS)
            .map(|steps| {
                let h = Self::hist(steps);
                self.nll(&h, before.0, before.1) - self.nll(&h, after.0, after.1)
            })
            .collect();
        gains.is_empty() || 3 * gains.iter().filter(|&&g| g > 0.0).count() >= 2 * gains.len()
    }

    /// Maximum-likelihood (share, shift index) among `shares`.
    fn fit(&self, h: &Hist, shares: &[f64]) -> (f64, usize) {
        let mut best = (1.0, 0, f64::INFINITY);
        for &share in shares {
            for i in 0..SHIFTS {
                let v = self.nll(h, share, i);
                if v < best.2 {
                    best = (share, i, v);
                }
            }
        }
        (best.0, best.1)
    }
}

/// The smallest motion per sweep beyond the sim's that is claimed, meters (1 m/s at 10 Hz).
const MIN_SEAM_SHIFT_M: f64 = 0.1;

/// The smallest share of the read seam steps that motion is claimed to move: it moves every
/// surface that faces it. A few steps moved alone are an edge of the scene at the seam.
const MIN_MOVED_SHARE: f64 = 0.6;

/// Seam steps on surfaces facing the motion that the sim and each half of the real
/// recording need for a fit: a few suffice, since motion moves every one of them by the same
/// metres per sweep, far beyond the scene's own steps at ordinary speeds.
const MIN_SEAM_STEPS: usize = 5;
/// Steps beside the seam that each recording needs for its reference.
const MIN_CONTROL_STEPS: usize = 30;

/// Seam steps a held-out scan needs for its own check of a seam shift.
const MIN_SCAN_SEAM_STEPS: usize = 3;

/// The seam steps of `obs` (covariate 1 + scan index) by scan.
fn scan_groups(obs: &Obs) -> Vec<Obs> {
    let mut groups: std::collections::BTreeMap<u32, Obs> = Default::default();
    for &(v, c) in obs.iter().filter(|x| x.1 > 0.5) {
        groups.entry(c as u32).or_default().push((v, 0.0));
    }
    groups.into_values().collect()
}

/// `motion_distortion`: no de-skew, a range step at the scan seam.
pub struct MotionFamily;

impl MotionFamily {
    /// Range step from the return fired first to the one fired last where they meet at
    /// the seam (offset 0), or (the controls) between two neighbouring columns `offset`
    /// columns beyond the meeting on either side, divided by the later return's
    /// [`motion_gain`]. On every row where both are kept, the meeting's returns are
    /// neighbours and the surface faces the motion: a sensor fires each beam at its own
    /// encoder angle whatever it does, so a row whose first and last returns lie columns apart
    /// meets across dropped rays, and a step across a hole is not one across the seam.
    fn steps(f: &ScanFeatures, seam: &Seam, offset: isize, out: &mut Obs) {
        let w = f.width;
        if w < 2 || f.normal.len() != f.range_m.len() {
            return;
        }
        for row in 0..f.height {
            let (first, last) = seam.meeting(row, w);
            let apart = (first + w - last) % w;
            if apart.min(w - apart) != 1 {
                continue;
            }
            let at = |c: usize| (c as isize + offset).rem_euclid(w as isize) as usize;
            let (first, last) = (at(first), at(last));
            let (a, b) = (row * w + first, row * w + last);
            let readable = |k: usize| f.kept[k] && !f.in_gap(k);
            if !readable(a) || !readable(b) {
                continue;
            }
            let dir = direction(f.elevation_rad[b], f.azimuth_rad[b]);
            if let Some(g) =
                shared_normal(f.normal[a], f.normal[b]).and_then(|n| motion_gain(n, dir))
            {
                out.push(((f.range_m[b] - f.range_m[a]) / g, f.range_m[a]));
            }
        }
    }
}

/// Smallest cosine between the normals estimated at the two returns of a step for them to
/// count as one surface. A normal estimated where a row's projection left holes can stand a
/// patch of ground up as a wall; its neighbour across the seam then disagrees.
const MIN_NORMAL_AGREEMENT: f32 = 0.9;

/// The normal of the surface both returns of a step lie on (their mean), where the two
/// estimates agree.
fn shared_normal(a: [f32; 3], b: [f32; 3]) -> Option<[f32; 3]> {
    let dot = a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    (dot >= MIN_NORMAL_AGREEMENT).then(|| {
        let m = [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
        let norm = (m[0] * m[0] + m[1] * m[1] + m[2] * m[2]).sqrt();
        m.map(|c| c / norm)
    })
}

/// Unit direction of a ray (sensor frame) from its elevation and azimuth.
fn direction(elevation: f32, azimuth: f32) -> [f32; 3] {
    let (se, ce) = elevation.sin_cos();
    let (sa, ca) = azimuth.sin_cos();
    [ce * ca, ce * sa, se]
}

impl ResidualFamily for MotionFamily {
    fn id(&self) -> &'static str {
        "motion_distortion"
    }
    /// Seam steps have covariate 1 + their scan's index, control steps covariate 0. Each
    /// scan's seam is where its own firing order starts over, else straight ahead.
    fn observations(&self, scans: &[ScanFeatures]) -> Obs {
        let mut obs = Vec::new();
        for (s, f) in scans.iter().enumerate() {
            let seam = (f.seam.clone()).unwrap_or_else(|| Seam::straight_ahead(f.width));
            let mut seam_steps = Vec::new();
            Self::steps(f, &seam, 0, &mut seam_steps);
            obs.extend(seam_steps.into_iter().map(|(v, _)| (v, 1.0 + s as f32)));
            for d in 1..=SEAM_CONTROL_COLUMNS as isize {
                let mut control = Vec::new();
                Self::steps(f, &seam, d, &mut control);
                Self::steps(f, &seam, -d, &mut control);
                obs.extend(control.into_iter().map(|(v, _)| (v, 0.0)));
            }
        }
        obs
    }
    fn fit(
        &self,
        sim: &Obs,
        train: &Obs,
        test: &Obs,
        ctx: &ResidualContext,
    ) -> Option<ResidualFit> {
        // Each recording's seam steps are judged against its own steps beside the seam,
        // which share its scene, noise and mixed pixels: only motion sets the seam apart.
        // The sim's motion per sweep (its physics as given) is the "before", the real one
        // fitted on training scans the "after".
        let pick = |o: &Obs, seam: bool| -> Obs {
            o.iter()
                .filter(|x| (x.1 > 0.5) == seam)
                .map(|x| (x.0, 0.0))
                .collect()
        };
        let by_scan = scan_groups(test);
        let (sim_ref, real_ref) = (pick(sim, false), pick(train, false));
        let (sim_seam, train, test) = (pick(sim, true), pick(train, true), pick(test, true));
        let enough_steps = sim_ref.len().min(real_ref.len()) >= MIN_CONTROL_STEPS
            && sim_seam.len().min(train.len()).min(test.len()) >= MIN_SEAM_STEPS;
        if !enough_steps {
            return None;
        }
        let (sim_model, real_model) = (SeamModel::new(&sim_ref), SeamModel::new(&real_ref));
        let (_, i_sim) = sim_model.fit(&SeamModel::hist(&sim_seam), &[1.0]);
        let shares: Vec<f64> = (6..=10).map(|i| 0.1 * f64::from(i)).collect();
        debug_assert!((shares[0] - MIN_MOVED_SHARE).abs() < 1e-9);
        let (h_train, h_test) = (SeamModel::hist(&train), SeamModel::hist(&test));
        let (share, i) = real_model.fit(&h_train, &shares);
        let (m_sim, m) = (seam_shift(i_sim), seam_shift(i));
        let nll = |share: f64, i: usize| real_model.nll(&h_test, share, i);
        // Where the seam steps are best explained by a few of them moved, those few are an
        // edge of the scene that lies at the seam in every scan (a road's edge seen at the
        // same azimuth from every point of a straight road), not the sensor's motion.
        let any_share: Vec<f64> = (1..=20).map(|i| 0.05 * f64::from(i)).collect();
        let (free_share, _) = real_model.fit(&h_train, &any_share);
        // A motion within a few centimetres per sweep of the sim's is within a scene's own
        // steps.
        let claimable = real_model.most_scans_fit_better(&by_scan, (1.0, i_sim), (share, i))
            && (m - m_sim).abs() >= MIN_SEAM_SHIFT_M
            && free_share >= MIN_MOVED_SHARE;
        let period = if ctx.period_s > 0.0 {
            ctx.period_s
        } else {
            0.1
        };
        let speed = m / period;
        let azimuth = ctx.sweep.map_or(0.0, |(azimuth, _)| azimuth);
        let mut params = Map::new();
        params.insert("motion_per_sweep_m".into(), json!(round4(m)));
        params.insert("sim_motion_per_sweep_m".into(), json!(round4(m_sim)));
        params.insert("speed_mps".into(), json!(round4(speed)));
        params.insert("moved_share".into(), json!(round4(share)));
        params.insert(
            "seam_azimuth_deg".into(),
            json!(round4(f64::from(azimuth.to_degrees()))),
        );
        if let Some((_, ccw)) = ctx.sweep {
            params.insert("counter_clockwise".into(), json!(ccw));
        }
        // Where the recording's speed is known the fit says how much of it goes undeskewed;
        // where it is not, the speed the seam measured is the effect's.
        let mut physics = Map::new();
        let effect = match ctx.speed_mps.filter(|v| *v > 0.1) {
            Some(known) => {
                let scale = speed / known;
                params.insert("scale".into(), json!(round4(scale)));
                json!({ "scale": round4(scale) })
            }
            None => json!({ "scale": 1.0, "speed_mps": round4(speed) }),
        };
        physics.insert("motion_distortion".into(), effect);
        Some(ResidualFit {
            id: self.id(),
            before_nll: nll(1.0, i_sim),
            after_nll: if claimable {
                nll(share, i)
            } else {
                nll(1.0, i_sim)
            },
            penalty: penalty(2, train.len()),
            test_obs: test.len(),
            params,
            physics,
            location: format!(
                "the scan seam at azimuth {:.0} deg ({}): surfaces facing the motion step by {:.2} m per sweep across it, {:.1} m/s{} (sim {m_sim:.2} m per sweep)",
                azimuth.to_degrees(),
                if ctx.sweep.is_some() {
                    "where the clouds' firing order starts over"
                } else {
                    "straight ahead: the clouds' order does not say where the sweep starts"
                },
                m,
                speed,
                match ctx.speed_mps {
                    Some(v) => format!(" against the recording's {v:.1} m/s"),
                    None =>
                        ", measured from the seam: the recording does not give its speed".into(),
                },
            ),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Motion observations of `scans` scans: per scan 40 seam steps read on surfaces facing
    /// the motion (the first `moved` of them moved by `shift` m per sweep) and 480 control
    /// steps, every step Gaussian with `sigma` m.
    fn seam_steps(scans: usize, seed: u64, sigma: f32, moved: usize, shift: f32) -> Obs {
        let mut rng = crate::util::rng::Rng::new(seed);
        let mut obs = Vec::new();
        for s in 0..scans {
            for k in 0..40 {
                let v = if k < moved { shift } else { 0.0 };
                obs.push((v + sigma * rng.normal(), 1.0 + s as f32));
            }
            obs.extend((0..480).map(|_| (sigma * rng.normal(), 0.0)));
        }
        obs
    }

    #[test]
    fn motion_on_a_share_of_the_seam_is_found_and_noise_alone_is_not() {
        let sim = seam_steps(15, 1, 0.05, 0, 0.0);
        let fit = |sigma: f32, moved: usize| {
            let train = seam_steps(8, 2, sigma, moved, 0.8);
            let test = seam_steps(7, 3, sigma, moved, 0.8);
            MotionFamily
                .fit(&sim, &train, &test, &ResidualContext::default())
                .expect("enough steps")
        };
        // 26 of 40 seam returns moved by 0.8 m: 8 m/s at 10 Hz.
        let moving = fit(0.05, 26);
        assert!(moving.significant(), "gain {}", moving.gain());
        assert!((moving.params["motion_per_sweep_m"].as_f64().unwrap() - 0.8).abs() < 0.11);
        assert!((moving.params["speed_mps"].as_f64().unwrap() - 8.0).abs() < 1.1);
        // The recording gives no speed: the effect carries the one measured.
        let speed = moving.physics["motion_distortion"]["speed_mps"]
            .as_f64()
            .unwrap();
        assert!((speed - 8.0).abs() < 1.1, "{speed}");
        assert!((moving.params["moved_share"].as_f64().unwrap() - 0.65).abs() < 0.11);
        // 12 of 40 moved: a few of the scene's surfaces, not every one facing the sensor.
        assert!(!fit(0.05, 12).significant());
        // Range noise widens the seam's steps and the control steps alike: no motion.
        let noisy = fit(0.3, 0);
        assert!(
            !noisy.significant(),
            "noise named motion: gain {}",
            noisy.gain()
        );
    }

    #[test]
    fn only_surfaces_facing_the_motion_are_read() {
        let (s, c) = (-10f32).to_radians().sin_cos();
        // The ground ahead: forward motion does not change its range.
        assert_eq!(motion_gain([0.0, 0.0, 1.0], [c, 0.0, s]), None);
        // A wall straight ahead comes a metre nearer per metre, one behind recedes.
        assert_eq!(motion_gain([-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]), Some(-1.0));
        assert_eq!(motion_gain([1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]), Some(1.0));
        // A wall along the road, seen behind at 80 deg: hardly moves, not read.
        let (s80, c80) = 100f32.to_radians().sin_cos();
        assert_eq!(motion_gain([0.0, -1.0, 0.0], [c80, s80, 0.0]), None);
    }

    #[test]
    fn an_edge_at_the_seam_of_every_scan_is_not_motion() {
        // A straight road's edge seen at the seam's azimuth from every point along it: the
        // same 4 of 40 seam steps 2.6 m apart in every scan, the other 36 flat.
        let sim = seam_steps(15, 1, 0.05, 0, 0.0);
        let train = seam_steps(8, 2, 0.05, 4, -2.6);
        let test = seam_steps(7, 3, 0.05, 4, -2.6);
        let edge = MotionFamily
            .fit(&sim, &train, &test, &ResidualContext::default())
            .expect("enough steps");
        assert!(!edge.significant(), "an edge named motion: {edge:?}");
    }
}
