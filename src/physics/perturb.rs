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

/// `motion_distortion`: no de-skew. A sensor fires every beam at its own encoder angle
/// whatever it does, so a ray fired `t` after the sweep start leaves from where the sensor
/// then is, displaced by `v t` (ego velocity `v`, in the sensor frame; a yaw turns the frame,
/// not the distance), and meets the surface it hit farther along or short of where a sensor at
/// rest met it: every return keeps its beam and column, only its range moves ([`moved_range`]).
/// The ground under a sensor driving over it is met at the same range; a wall ahead comes
/// nearer by `v t`. `scale` multiplies `t` (1 = full, 0 = de-skewed); `speed_mps`, where
/// given, replaces the recording's speed, along its heading. Where a sweep's first and last
/// columns meet, surfaces that face the motion step by `v * period`: a seam.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MotionDistortion {
    #[serde(default = "yes")]
    pub enabled: bool,
    #[serde(default = "unit_scale")]
    pub scale: f32,
    /// Ego speed (m/s) in place of the recording's, along its heading (the sensor's +x where
    /// it stands still): what a diagnosis measured where the recording does not say.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub speed_mps: Option<f32>,
}

fn unit_scale() -> f32 {
    1.0
}

/// Largest range change per metre of displacement: a surface met nearly edge-on would move
/// its hit point without bound under the plane model, while real surfaces end.
const MAX_RANGE_CHANGE_PER_M: f32 = 3.0;

/// The range at which a ray of unit direction `dir`, fired from a sensor displaced by
/// `shift`, meets the surface that a sensor at rest met at `range` with unit normal
/// `normal`: the plane `n . (x - r d) = 0` is met at `r - n . s / n . d`. Without a normal
/// the surface is taken to face the ray (`|r d - s|`).
pub fn moved_range(range: f32, dir: [f32; 3], normal: [f32; 3], shift: [f32; 3]) -> f32 {
    let dot = |a: [f32; 3], b: [f32; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let limit = MAX_RANGE_CHANGE_PER_M * dot(shift, shift).sqrt();
    let n_dot_d = dot(normal, dir);
    let change = if n_dot_d.abs() > 1e-3 {
        -dot(normal, shift) / n_dot_d
    } else if dot(normal, normal) > 0.5 {
        0.0 // a surface met edge-on: no plane model, no change
    } else {
        let p = dir.map(|c| c * range);
        let q = [p[0] - shift[0], p[1] - shift[1], p[2] - shift[2]];
        dot(q, q).sqrt() - range
    };
    (range + change.clamp(-limit, limit)).max(1e-3)
}

impl MotionDistortion {
    /// The ego velocity in the sensor frame, m/s: along the sensor's level (x-y) plane, since
    /// a vehicle follows the ground it stands on while a recording's velocity may be level
    /// where its ground slopes (a velocity into a sloped road would move the road).
    fn velocity(&self, scan: &SimScan) -> [f32; 3] {
        let v = scan.pose.velocity_mps;
        let world = crate::sim::geometry::v3(v[0], v[1], v[2]);
        let sensor = scan.pose.to_sensor(world);
        let level = crate::sim::geometry::v3(sensor.x, sensor.y, 0.0);
        let heading = if level.length() > 1e-3 {
            level.normalized()
        } else {
            crate::sim::geometry::v3(1.0, 0.0, 0.0)
        };
        (heading * self.speed_mps.unwrap_or(world.length())).to_array()
    }
}

impl Effect for MotionDistortion {
    fn id(&self) -> &'static str {
        "motion_distortion"
    }
    fn perturb(&self, scan: &mut SimScan, _ctx: &EffectContext) {
        let v = self.velocity(scan);
        for k in 0..scan.len() {
            if !scan.is_return(k) {
                continue;
            }
            let t = scan.time_s[k] * self.scale;
            let r = scan.image.range_m[k];
            let dir = scan.image.xyz[k].map(|c| c / r);
            let shift = v.map(|c| c * t);
            scan.set_range(k, moved_range(r, dir, scan.normal[k], shift));
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
    fn motion_distortion_moves_surfaces_facing_the_motion_and_not_the_ground() {
        let (ideal, real) = before_after(
            Box::new(MotionDistortion {
                enabled: true,
                scale: 1.0,
                speed_mps: None,
            }),
            4,
        );
        let v = ideal.pose.velocity_mps[0];
        assert!(v > 5.0);
        // Range change of each return, and what the plane of its surface says: a ray fired
        // `t` into the sweep from `v t` farther along meets it `-n_x v t / n . d` farther.
        let facing_up = |k: usize| ideal.normal[k][2] > 0.99999;
        let changes: Vec<(usize, f32, f32)> = (0..ideal.len())
            .filter(|&k| ideal.is_return(k))
            .map(|k| {
                let (n, r) = (ideal.normal[k], ideal.image.range_m[k]);
                let d = ideal.image.xyz[k].map(|c| c / r);
                let n_dot_d = n[0] * d[0] + n[1] * d[1] + n[2] * d[2];
                let want = -n[0] * v * ideal.time_s[k] / n_dot_d;
                (
                    k,
                    real.image.range_m[k] - r,
                    if n_dot_d.abs() > 0.5 { want } else { f32::NAN },
                )
            })
            .collect();
        // Level ground is met at the same range however far the sensor drove.
        let ground: Vec<f32> = (changes.iter())
            .filter(|(k, ..)| facing_up(*k))
            .map(|(_, c, _)| *c)
            .collect();
        assert!(ground.len() > 1000);
        assert!(ground.iter().all(|c| c.abs() < 1e-3), "the ground moved");
        // Walls across the heading, met within 60 deg of head-on, move as their plane says,
        // most of them by a good part of a sweep's motion.
        let walls: Vec<(f32, f32)> = (changes.iter())
            .filter(|(k, _, want)| ideal.normal[*k][0].abs() > 0.95 && want.is_finite())
            .map(|(_, c, want)| (*c, *want))
            .collect();
        assert!(walls.len() > 50, "{}", walls.len());
        for (c, want) in &walls {
            assert!((c - want).abs() < 0.01 * v * 0.1, "{c} vs {want}");
        }
        let large = walls
            .iter()
            .filter(|(c, _)| c.abs() > 0.2 * v * 0.1)
            .count();
        assert!(2 * large > walls.len(), "{large} of {}", walls.len());
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
    fn a_plane_is_met_where_the_moved_ray_crosses_it() {
        // Ground 1.7 m below, a ray 10 deg down: moving 1 m forward keeps its range.
        let (s, c) = (-10f32).to_radians().sin_cos();
        let r = 1.7 / -s;
        let up = [0.0, 0.0, 1.0];
        assert!((moved_range(r, [c, 0.0, s], up, [1.0, 0.0, 0.0]) - r).abs() < 1e-5);
        // A wall 20 m ahead met head-on comes 1 m nearer; seen 30 deg aside, 1 m / cos 30.
        let back = [-1.0, 0.0, 0.0];
        assert!((moved_range(20.0, [1.0, 0.0, 0.0], back, [1.0, 0.0, 0.0]) - 19.0).abs() < 1e-5);
        let (s30, c30) = 30f32.to_radians().sin_cos();
        let r30 = 20.0 / c30;
        let want = r30 - 1.0 / c30;
        assert!((moved_range(r30, [c30, s30, 0.0], back, [1.0, 0.0, 0.0]) - want).abs() < 1e-4);
        // No normal: the surface faces the ray.
        assert!(
            (moved_range(20.0, [1.0, 0.0, 0.0], [0.0; 3], [1.0, 0.0, 0.0]) - 19.0).abs() < 1e-5
        );
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
