//! Randomised sensors (beams, spacing, columns, mounting height, cloud layout) and the
//! ideal scan one casts in a scene.

use rangegan_mcap::lidar::{RangeImage, Scan, SensorProfile};
use rangegan_mcap::sim::raycast::intensity;
use rangegan_mcap::sim::{Material, SensorPose, SimScan};

use super::{Rng, Scene};

/// A randomised sensor: beams, spacing, columns, mounting height, cloud layout, and where
/// and which way its sweep turns.
#[derive(Debug, Clone)]
pub struct Sensor {
    pub profile: SensorProfile,
    pub height_m: f32,
    pub organized: bool,
    pub ring_field: bool,
    /// Whether each point carries its firing time.
    pub time_field: bool,
    /// Azimuth where each sweep starts (and the previous one ends), radians: straight
    /// ahead as KITTI's, behind as an Ouster's, or anywhere a driver cuts the scan.
    pub sweep_start_rad: f32,
    /// Whether the sweep turns clockwise seen from above (towards negative azimuth), as a
    /// Velodyne's does.
    pub clockwise: bool,
}

impl Sensor {
    /// `beams` lasers between a drawn top and bottom elevation, either evenly
    /// spaced or denser near the horizon.
    pub fn random(rng: &mut Rng, beams: usize) -> Sensor {
        let (top, bottom) = match beams {
            16 => (rng.range(10.0, 15.0), -rng.range(10.0, 15.0)),
            32 => (rng.range(8.0, 15.0), -rng.range(16.0, 30.0)),
            64 => (rng.range(2.0, 16.0), -rng.range(16.0, 26.0)),
            _ => (rng.range(10.0, 22.0), -rng.range(16.0, 22.0)),
        };
        let dense = rng.chance(0.5);
        let elevation_deg: Vec<f32> = (0..beams)
            .map(|i| {
                let u = i as f32 / (beams - 1) as f32;
                // Horizon-dense: a cubic ease that packs beams near the middle.
                let s = if dense {
                    let c = 2.0 * u - 1.0;
                    0.5 + 0.5 * (0.6 * c + 0.4 * c * c * c)
                } else {
                    u
                };
                top + (bottom - top) * s
            })
            .collect();
        let columns = match beams {
            16 => rng.pick(&[1024usize, 2048]),
            32 => rng.pick(&[1024usize, 1800]),
            64 => rng.pick(&[512usize, 1024]),
            _ => 512,
        };
        Sensor {
            profile: SensorProfile {
                name: format!("testgen-{beams}"),
                elevation_deg,
                azimuth_offset_deg: None,
                columns,
                min_range_m: rng.range(0.5, 2.0),
                max_range_m: rng.range(80.0, 120.0),
            },
            height_m: rng.range(1.2, 2.2),
            organized: rng.chance(0.5),
            ring_field: rng.chance(0.5),
            time_field: rng.chance(0.5),
            // Drivers cut the sweep ahead (KITTI) or behind (Ouster), give or take 40 deg; a
            // seam across the heading hides motion (docs/diagnose.md).
            sweep_start_rad: rng.pick(&[0.0, std::f32::consts::PI]) + rng.range(-0.7, 0.7),
            clockwise: rng.chance(0.5),
        }
    }

    /// When, within a sweep of `period_s`, the beams fire at azimuth `a` (radians).
    pub fn firing_time_s(&self, a: f32, period_s: f32) -> f32 {
        let turned = if self.clockwise {
            self.sweep_start_rad - a
        } else {
            a - self.sweep_start_rad
        };
        turned.rem_euclid(std::f32::consts::TAU) / std::f32::consts::TAU * period_s
    }

    pub fn describe(&self) -> String {
        format!(
            "{} beams x {} ({:.1}..{:.1} deg, {:.2} m up, {}, {}, {}, sweep from {:.0} deg {})",
            self.profile.beams(),
            self.profile.columns,
            self.profile.elevation_deg[0],
            self.profile.elevation_deg[self.profile.beams() - 1],
            self.height_m,
            if self.organized {
                "organized"
            } else {
                "unorganized"
            },
            if self.ring_field {
                "ring field"
            } else {
                "no ring field"
            },
            if self.time_field {
                "time field"
            } else {
                "no time field"
            },
            self.sweep_start_rad.to_degrees(),
            if self.clockwise {
                "clockwise"
            } else {
                "counter-clockwise"
            },
        )
    }
}

/// Scans a side and their spacing in time.
pub const SCANS: u32 = 16;
pub(super) const STRIDE_S: f32 = 0.3;

/// Ideal scan `index` of `scene` with `sensor`: one ray per pixel from the pose
/// at the scan start, each column timed within the 10 Hz sweep as the sensor turns
/// (its motion during the sweep is the `motion_distortion` effect's).
pub fn cast_scan(scene: &Scene, sensor: &Sensor, index: u32) -> SimScan {
    let profile = &sensor.profile;
    let angles = profile.angle_grid();
    let (h, w) = (angles.height, angles.width);
    let t = index as f32 * STRIDE_S;
    let origin = [scene.speed_mps * t, scene.lane_y_m, sensor.height_m];
    // Cull: each object under the columns its footprint spans.
    let mut by_column: Vec<Vec<u32>> = vec![Vec::new(); w];
    let col_of = |a: f32| {
        let j = (std::f32::consts::PI - a) / std::f32::consts::TAU * w as f32;
        j.rem_euclid(w as f32) as usize % w
    };
    for (i, obj) in scene.objects.iter().enumerate() {
        let (c, r) = obj.footprint();
        let (dx, dy) = (c[0] - origin[0], c[1] - origin[1]);
        let dist = (dx * dx + dy * dy).sqrt();
        if dist - r > profile.max_range_m {
            continue;
        }
        if dist <= r + 0.5 {
            by_column.iter_mut().for_each(|v| v.push(i as u32));
            continue;
        }
        let a = dy.atan2(dx);
        let half = (r / dist).asin() + 2.0 * std::f32::consts::TAU / w as f32;
        let (ja, jb) = (col_of(a + half), col_of(a - half));
        let mut j = ja;
        loop {
            by_column[j].push(i as u32);
            if j == jb {
                break;
            }
            j = (j + 1) % w;
        }
    }
    let mut image = RangeImage::empty(angles);
    let n = h * w;
    let mut material = vec![Material::None; n];
    let mut incidence_rad = vec![0.0f32; n];
    let mut normals = vec![[0.0f32; 3]; n];
    let mut reflectivity = vec![0.0f32; n];
    let mut true_label = vec![0u32; n];
    let period = 0.1f32;
    let time_s: Vec<f32> = (0..n)
        .map(|k| sensor.firing_time_s(image.angles.azimuth_rad[k], period))
        .collect();
    for k in 0..n {
        let d = image.angles.direction(k);
        let Some((t_hit, normal, s)) =
            scene.cast(origin, d, profile.max_range_m, &by_column[k % w])
        else {
            continue;
        };
        let cos_inc = (-(normal[0] * d[0] + normal[1] * d[1] + normal[2] * d[2])).clamp(0.0, 1.0);
        material[k] = s.material;
        incidence_rad[k] = cos_inc.acos();
        // The sensor's axes are the world's: the normal, turned to face the ray.
        let facing = if cos_inc > 0.0 { 1.0 } else { -1.0 };
        normals[k] = normal.map(|c| c * facing);
        reflectivity[k] = s.reflectivity;
        true_label[k] = s.label;
        if t_hit < profile.min_range_m {
            continue;
        }
        image.range_m[k] = t_hit;
        image.xyz[k] = d.map(|c| c * t_hit);
        image.intensity[k] = intensity(s.reflectivity, cos_inc, t_hit);
        image.label[k] = s.label;
        image.point_index[k] = k as u32;
    }
    let true_range_m = image.range_m.clone();
    SimScan {
        image,
        material,
        incidence_rad,
        normal: normals,
        reflectivity,
        time_s,
        true_range_m,
        true_label,
        index,
        start_time_s: f64::from(t),
        pose: SensorPose {
            origin: rangegan_mcap::sim::geometry::v3(origin[0], origin[1], origin[2]),
            axes: [
                rangegan_mcap::sim::geometry::v3(1.0, 0.0, 0.0),
                rangegan_mcap::sim::geometry::v3(0.0, 1.0, 0.0),
                rangegan_mcap::sim::geometry::v3(0.0, 0.0, 1.0),
            ],
            velocity_mps: [scene.speed_mps, 0.0, 0.0],
            yaw_rate_rps: 0.0,
            yaw_rad: 0.0,
        },
        min_range_m: profile.min_range_m,
        max_range_m: profile.max_range_m,
    }
}

/// `scan` as the sensor's driver writes it: organized, its columns in firing order
/// (the first fired first), or unorganized, ring by ring, each ring in firing order; a
/// ring field and a time field where the sensor has them.
pub fn cloud(scan: &SimScan, sensor: &Sensor) -> Scan {
    let full = scan.to_scan(true);
    let (h, w) = (scan.image.height, scan.image.width);
    let mut columns: Vec<usize> = (0..w).collect();
    columns.sort_by(|&a, &b| scan.time_s[a].total_cmp(&scan.time_s[b]));
    let order: Vec<usize> = (0..h)
        .flat_map(|i| columns.iter().map(move |&j| i * w + j))
        .filter(|&k| sensor.organized || scan.is_return(k))
        .collect();
    let pick = |v: &Option<Vec<f32>>| v.as_ref().map(|v| order.iter().map(|&k| v[k]).collect());
    Scan {
        xyz: order.iter().map(|&k| full.xyz[k]).collect(),
        intensity: pick(&full.intensity),
        ring: (full.ring.as_ref())
            .filter(|_| sensor.ring_field)
            .map(|r| order.iter().map(|&k| r[k]).collect()),
        time_s: pick(&full.time_s).filter(|_| sensor.time_field),
        label: (full.label.as_ref()).map(|l| order.iter().map(|&k| l[k]).collect()),
        height: if sensor.organized { h } else { 1 },
        width: if sensor.organized { w } else { order.len() },
    }
}
