//! Perturbations: effects that move, dim or add returns rather than drop them.
//! Each is a closed-form range or intensity perturbation given the ray's features.

use serde::{Deserialize, Serialize};

use super::{Effect, EffectContext, RayFeatures, salt};
use crate::sim::SimScan;

fn yes() -> bool {
    true
}

/// `range_noise`: Gaussian range error growing with distance,
/// `d' = d + N(0, sigma0_m + k * d)`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RangeNoise {
    #[serde(default = "yes")]
    pub enabled: bool,
    pub sigma0_m: f32,
    pub k: f32,
}

impl Effect for RangeNoise {
    fn id(&self) -> &'static str {
        "range_noise"
    }
    fn perturb(&self, scan: &mut SimScan, ctx: &EffectContext) {
        let s = salt(self.id());
        for k in 0..scan.len() {
            if scan.is_return(k) {
                let d = scan.image.range_m[k];
                let sigma = self.sigma0_m + self.k * d;
                scan.set_range(k, (d + sigma * ctx.gaussian(s, k)).max(1e-3));
            }
        }
    }
}

/// `range_quantization`: ranges reported in steps of `step_m`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RangeQuantization {
    #[serde(default = "yes")]
    pub enabled: bool,
    pub step_m: f32,
}

impl Effect for RangeQuantization {
    fn id(&self) -> &'static str {
        "range_quantization"
    }
    fn perturb(&self, scan: &mut SimScan, _ctx: &EffectContext) {
        if self.step_m <= 0.0 {
            return;
        }
        for k in 0..scan.len() {
            if scan.is_return(k) {
                let d = scan.image.range_m[k];
                scan.set_range(
                    k,
                    ((d / self.step_m).round() * self.step_m).max(self.step_m),
                );
            }
        }
    }
}

/// `mixed_pixels`: the beam's footprint straddles a depth edge and the return
/// averages both surfaces. A pixel whose ideal range differs from a 4-neighbour's
/// by more than `min_gap_m` becomes mixed with probability `prob`; its range is
/// then uniform between the near and far range.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MixedPixels {
    #[serde(default = "yes")]
    pub enabled: bool,
    pub prob: f32,
    pub min_gap_m: f32,
}

impl MixedPixels {
    /// The (near, far) ranges of the widest depth edge at pixel `k`, if any.
    pub fn edge(&self, scan: &SimScan, k: usize) -> Option<(f32, f32)> {
        let (h, w) = (scan.height(), scan.width());
        let (row, col) = (k / w, k % w);
        let d = scan.true_range_m[k];
        if d <= 0.0 {
            return None;
        }
        let mut neighbours = [None; 4];
        neighbours[0] = Some(row * w + (col + w - 1) % w);
        neighbours[1] = Some(row * w + (col + 1) % w);
        if row > 0 {
            neighbours[2] = Some(k - w);
        }
        if row + 1 < h {
            neighbours[3] = Some(k + w);
        }
        neighbours
            .into_iter()
            .flatten()
            .map(|n| scan.true_range_m[n])
            .filter(|&dn| dn > 0.0 && (dn - d).abs() > self.min_gap_m)
            .max_by(|a, b| (a - d).abs().total_cmp(&(b - d).abs()))
            .map(|dn| (d.min(dn), d.max(dn)))
    }
}

impl Effect for MixedPixels {
    fn id(&self) -> &'static str {
        "mixed_pixels"
    }
    fn perturb(&self, scan: &mut SimScan, ctx: &EffectContext) {
        let s = salt(self.id());
        let edges: Vec<(usize, f32, f32)> = (0..scan.len())
            .filter(|&k| scan.is_return(k))
            .filter_map(|k| self.edge(scan, k).map(|(near, far)| (k, near, far)))
            .collect();
        for (k, near, far) in edges {
            if ctx.uniform(s, k) < self.prob {
                let u = ctx.uniform(s ^ 0x5eed, k);
                scan.set_range(k, near + u * (far - near));
            }
        }
    }
}

/// `motion_distortion`: no de-skew. A point measured `t` after the sweep start is
/// reported in the sensor frame of that instant, along the direction the sensor fired it:
/// its range becomes the distance `|Rz(-w t) (p - v t)| = |p - v t|` from where the sensor
/// then was, with the ego velocity `v` and yaw rate `w`, times `scale` (1 = full,
/// 0 = de-skewed). A sensor fires at its own encoder angle whatever it does, so every
/// return keeps its beam and column: only ranges move. The scan's first and last columns
/// disagree by `v * period`: a seam.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MotionDistortion {
    #[serde(default = "yes")]
    pub enabled: bool,
    #[serde(default = "unit_scale")]
    pub scale: f32,
}

fn unit_scale() -> f32 {
    1.0
}

impl Effect for MotionDistortion {
    fn id(&self) -> &'static str {
        "motion_distortion"
    }
    fn perturb(&self, scan: &mut SimScan, _ctx: &EffectContext) {
        // A yaw turns the frame, not the distance, so only the velocity moves a range.
        let v = scan.pose.velocity_mps;
        for k in 0..scan.len() {
            if !scan.is_return(k) {
                continue;
            }
            let t = scan.time_s[k] * self.scale;
            let p = scan.image.xyz[k];
            let q = [p[0] - v[0] * t, p[1] - v[1] * t, p[2] - v[2] * t];
            scan.set_range(
                k,
                (q[0] * q[0] + q[1] * q[1] + q[2] * q[2]).sqrt().max(1e-3),
            );
        }
    }
}

/// `intensity_noise`: multiplicative Gaussian intensity noise, `I' = I (1 + sigma_rel N)`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IntensityNoise {
    #[serde(default = "yes")]
    pub enabled: bool,
    pub sigma_rel: f32,
}

impl Effect for IntensityNoise {
    fn id(&self) -> &'static str {
        "intensity_noise"
    }
    fn perturb(&self, scan: &mut SimScan, ctx: &EffectContext) {
        let s = salt(self.id());
        for k in 0..scan.len() {
            if scan.is_return(k) {
                let i = scan.image.intensity[k] * (1.0 + self.sigma_rel * ctx.gaussian(s, k));
                scan.image.intensity[k] = i.clamp(0.0, 1.0);
            }
        }
    }
}

/// `atmosphere`: rain or fog with extinction coefficient `extinction_per_m`. A
/// ray loses its return with `p = 1 - exp(-2 alpha d)`, kept returns are dimmed by
/// `exp(-2 alpha d)`, and with `clutter_prob` per ray a droplet return appears at
/// `min_range + Exp(clutter_mean_range_m)` if that is nearer than the surface
/// (label 0, low intensity).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Atmosphere {
    #[serde(default = "yes")]
    pub enabled: bool,
    pub extinction_per_m: f32,
    #[serde(default)]
    pub clutter_prob: f32,
    #[serde(default = "clutter_range")]
    pub clutter_mean_range_m: f32,
}

fn clutter_range() -> f32 {
    3.0
}

impl Effect for Atmosphere {
    fn id(&self) -> &'static str {
        "atmosphere"
    }
    fn drops(&self) -> bool {
        true
    }
    fn drop_prob(&self, f: &RayFeatures) -> f32 {
        1.0 - (-2.0 * self.extinction_per_m * f.range_m.max(0.0)).exp()
    }
    fn perturb(&self, scan: &mut SimScan, ctx: &EffectContext) {
        let s = salt(self.id()) ^ 0xc1u64;
        for k in 0..scan.len() {
            if scan.is_return(k) {
                scan.image.intensity[k] *=
                    (-2.0 * self.extinction_per_m * scan.image.range_m[k]).exp();
            }
            if self.clutter_prob > 0.0 && ctx.uniform(s, k) < self.clutter_prob {
                let r = scan.min_range_m
                    - self.clutter_mean_range_m * ctx.uniform(s ^ 1, k).max(1e-7).ln();
                let current = scan.image.range_m[k];
                if r < scan.max_range_m && (current <= 0.0 || r < current) {
                    let d = scan.image.angles.direction(k);
                    scan.image.range_m[k] = r;
                    scan.image.xyz[k] = d.map(|c| c * r);
                    scan.image.intensity[k] = 0.02;
                    scan.image.label[k] = 0;
                    scan.image.point_index[k] = k as u32;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::dropout::tests::before_after;
    use super::*;

    fn residuals(ideal: &SimScan, real: &SimScan) -> Vec<(usize, f32)> {
        (0..ideal.len())
            .filter(|&k| ideal.is_return(k) && real.is_return(k))
            .map(|k| (k, real.image.range_m[k] - ideal.image.range_m[k]))
            .collect()
    }

    #[test]
    fn range_noise_sigma_grows_linearly_with_range() {
        let (ideal, real) = before_after(
            Box::new(RangeNoise {
                enabled: true,
                sigma0_m: 0.02,
                k: 0.002,
            }),
            1,
        );
        let res = residuals(&ideal, &real);
        let std_in = |lo: f32, hi: f32| {
            let v: Vec<f32> = res
                .iter()
                .filter(|(k, _)| (lo..hi).contains(&ideal.true_range_m[*k]))
                .map(|r| r.1)
                .collect();
            let m = v.iter().sum::<f32>() / v.len() as f32;
            (
                (v.iter().map(|x| (x - m) * (x - m)).sum::<f32>() / v.len() as f32).sqrt(),
                m,
            )
        };
        let (near, m_near) = std_in(2.0, 8.0);
        let (far, _) = std_in(40.0, 60.0);
        // sigma(5 m) ~ 0.03, sigma(50 m) ~ 0.12
        assert!(
            (near - 0.03).abs() < 0.006 && (far - 0.12).abs() < 0.025,
            "near {near} far {far}"
        );
        assert!(m_near.abs() < 0.003);
        // Directions stay on the pixel ray.
        let k = res[0].0;
        let (p, q) = (ideal.image.xyz[k], real.image.xyz[k]);
        let cross = [
            p[1] * q[2] - p[2] * q[1],
            p[2] * q[0] - p[0] * q[2],
            p[0] * q[1] - p[1] * q[0],
        ];
        assert!(cross.iter().map(|c| c.abs()).sum::<f32>() < 1e-2);
    }

    #[test]
    fn range_quantization_snaps_to_steps() {
        let (ideal, real) = before_after(
            Box::new(RangeQuantization {
                enabled: true,
                step_m: 0.05,
            }),
            2,
        );
        let res = residuals(&ideal, &real);
        assert!(res.iter().all(|(_, r)| r.abs() <= 0.0251));
        assert!(res.iter().any(|(_, r)| r.abs() > 0.01));
        for (k, _) in res.iter().take(100) {
            let q = real.image.range_m[*k] / 0.05;
            assert!((q - q.round()).abs() < 1e-3);
        }
        assert_eq!(ideal.image.valid_count(), real.image.valid_count());
    }

    #[test]
    fn mixed_pixels_appear_between_surfaces_at_depth_edges_only() {
        let e = MixedPixels {
            enabled: true,
            prob: 0.5,
            min_gap_m: 1.0,
        };
        let (ideal, real) = before_after(Box::new(e.clone()), 3);
        let mut at_edge = 0;
        let mut moved_at_edge = 0;
        for (k, r) in residuals(&ideal, &real) {
            match e.edge(&ideal, k) {
                Some((near, far)) => {
                    at_edge += 1;
                    if r.abs() > 1e-6 {
                        moved_at_edge += 1;
                    }
                    let d = real.image.range_m[k];
                    assert!(d >= near - 1e-3 && d <= far + 1e-3);
                }
                None => assert_eq!(r, 0.0, "pixel {k} moved away from any depth edge"),
            }
        }
        let share = moved_at_edge as f32 / at_edge as f32;
        assert!(
            at_edge > 500 && (share - 0.5).abs() < 0.06,
            "{moved_at_edge} of {at_edge}"
        );
    }

    #[test]
    fn motion_distortion_opens_a_seam_at_the_scan_start() {
        let (ideal, real) = before_after(
            Box::new(MotionDistortion {
                enabled: true,
                scale: 1.0,
            }),
            4,
        );
        let v = ideal.pose.velocity_mps[0];
        assert!(v > 5.0);
        let w = ideal.width();
        // Shift of each return along x: -v t, so ~0 just after the start (azimuth 0,
        // straight ahead, column w/2) and ~v * 0.1 s just before it.
        let shift = |col: usize| {
            let v: Vec<f32> = (0..ideal.height())
                .map(|r| r * w + col)
                .filter(|&k| ideal.is_return(k))
                .map(|k| real.image.xyz[k][0] - ideal.image.xyz[k][0])
                .collect();
            v.iter().sum::<f32>() / v.len().max(1) as f32
        };
        let after_start = shift(w / 2 - 1); // azimuth just above 0
        let before_end = shift(w / 2); // azimuth just below 0: measured last
        assert!(after_start.abs() < 0.05, "{after_start}");
        assert!(
            (before_end + v * 0.1).abs() < 0.1,
            "{before_end} vs {}",
            -v * 0.1
        );
        // The rear (column 0, half a sweep) moved half as far.
        assert!((shift(0) + v * 0.05).abs() < 0.1, "{}", shift(0));
        // Every return keeps the direction it was fired in: its pixel.
        for k in (0..ideal.len()).filter(|&k| ideal.is_return(k)) {
            let (a, b) = (ideal.image.xyz[k], real.image.xyz[k]);
            let (ra, rb) = (ideal.image.range_m[k], real.image.range_m[k]);
            for i in 0..3 {
                assert!((a[i] / ra - b[i] / rb).abs() < 1e-4, "pixel {k} turned");
            }
        }
    }

    #[test]
    fn intensity_noise_keeps_the_mean_and_adds_spread() {
        let (ideal, real) = before_after(
            Box::new(IntensityNoise {
                enabled: true,
                sigma_rel: 0.2,
            }),
            5,
        );
        let ratios: Vec<f32> = (0..ideal.len())
            .filter(|&k| ideal.is_return(k) && ideal.image.intensity[k] > 0.05)
            .map(|k| real.image.intensity[k] / ideal.image.intensity[k])
            .collect();
        let m = ratios.iter().sum::<f32>() / ratios.len() as f32;
        let sd =
            (ratios.iter().map(|x| (x - m) * (x - m)).sum::<f32>() / ratios.len() as f32).sqrt();
        assert!(
            (m - 1.0).abs() < 0.02 && (sd - 0.2).abs() < 0.03,
            "mean {m} sd {sd}"
        );
        assert_eq!(ideal.image.range_m, real.image.range_m);
    }

    #[test]
    fn atmosphere_drops_far_rays_and_adds_near_clutter() {
        let e = Atmosphere {
            enabled: true,
            extinction_per_m: 0.01,
            clutter_prob: 0.02,
            clutter_mean_range_m: 3.0,
        };
        let (ideal, real) = before_after(Box::new(e), 6);
        let drop = |lo: f32, hi: f32| {
            let sel: Vec<usize> = (0..ideal.len())
                .filter(|&k| (lo..hi).contains(&ideal.true_range_m[k]))
                .collect();
            sel.iter().filter(|&&k| !real.is_return(k)).count() as f32 / sel.len() as f32
        };
        assert!(
            drop(2.0, 6.0) < 0.15 && drop(40.0, 60.0) > 0.5,
            "{} {}",
            drop(2.0, 6.0),
            drop(40.0, 60.0)
        );
        let clutter = (0..ideal.len())
            .filter(|&k| {
                real.is_return(k) && real.image.label[k] == 0 && real.image.range_m[k] < 10.0
            })
            .count();
        let rate = clutter as f32 / ideal.len() as f32;
        assert!(rate > 0.005 && rate < 0.03, "{rate}");
    }
}
