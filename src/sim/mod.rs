//! The LiDAR scene simulator: procedural street scenes from a seed ([`scene`]), an
//! ego drive through them ([`trajectory`]), and ideal ray casting of any
//! [`SensorProfile`](crate::lidar::SensorProfile) with a BVH ([`bvh`], [`raycast`]).
//! Every scan carries per-pixel ground truth (label, material, incidence angle,
//! reflectivity, time) for the physics layer ([`crate::physics`]), which turns the
//! ideal scan into a realistic one. Randomness is keyed, never sequential across
//! threads ([`crate::util::rng`]). Comparison with real KITTI scans lives in [`realism`].
//!
//! ```
//! use rangegan_mcap::lidar::SensorProfile;
//! use rangegan_mcap::sim::{Simulator, SceneConfig};
//! let profile = SensorProfile::kitti_hdl64e().with_columns(256);
//! let sim = Simulator::new(SceneConfig { seed: 1, duration_s: 0.3, ..Default::default() }, profile);
//! let scan = sim.scan(0);
//! assert!(scan.keep_rate() > 0.5);
//! ```

mod builder;
pub mod bvh;
pub mod geometry;
pub mod material;
pub mod raycast;
pub mod realism;
pub mod scene;
mod street;
pub mod trajectory;

pub use material::{Material, label};
pub use raycast::{SensorPose, SimScan, SweepTiming};
pub use scene::{Scene, SceneConfig};

use crate::lidar::SensorProfile;
use geometry::v3;

/// Wraps an angle to (-pi, pi].
pub fn wrap_angle(a: f32) -> f32 {
    crate::lidar::profile::wrap_pi(a)
}

/// A scene, a sensor and its sweep timing: makes the ideal scans of a drive.
#[derive(Debug, Clone)]
pub struct Simulator {
    pub scene: Scene,
    pub profile: SensorProfile,
    pub timing: SweepTiming,
}

impl Simulator {
    /// Generates the scene for `config` (its `max_range_m` is raised to the
    /// profile's) and pairs it with `profile`, sweeping at 10 Hz.
    pub fn new(mut config: SceneConfig, profile: SensorProfile) -> Self {
        config.max_range_m = config.max_range_m.max(profile.max_range_m);
        Simulator {
            scene: Scene::generate(config),
            profile,
            timing: SweepTiming::default(),
        }
    }

    /// Start time of scan `index` from the start of the drive.
    pub fn scan_time(&self, index: u32) -> f64 {
        index as f64 * self.timing.period_s as f64
    }

    /// The sensor pose at time `t_s`: on the ego route, `sensor_height_m` above the
    /// road, pitched and rolled with the ground slope.
    pub fn sensor_pose(&self, t_s: f64) -> SensorPose {
        let (p, z) = self.scene.ego_pose(t_s as f32);
        let [gx, gy] = self.scene.layout.slope;
        let (s, c) = p.yaw.sin_cos();
        let up = v3(-gx, -gy, 1.0).normalized();
        let forward = v3(c, s, gx * c + gy * s).normalized();
        let left = up.cross(forward).normalized();
        let forward = left.cross(up);
        let yaw_rate = self.scene.trajectory.yaw_rate_at(t_s as f32);
        SensorPose {
            origin: v3(p.x, p.y, z + self.scene.config.sensor_height_m),
            axes: [forward, left, up],
            velocity_mps: [self.scene.trajectory.speed_mps, 0.0, 0.0],
            yaw_rate_rps: yaw_rate,
            yaw_rad: p.yaw,
        }
    }

    /// The ideal scan `index` (no sensor physics).
    pub fn scan(&self, index: u32) -> SimScan {
        let t = self.scan_time(index);
        raycast::cast_scan(
            &self.scene,
            &self.profile,
            &self.sensor_pose(t),
            &self.timing,
            t,
            index,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn small() -> Simulator {
        Simulator::new(
            SceneConfig {
                seed: 11,
                duration_s: 1.0,
                ..Default::default()
            },
            SensorProfile::kitti_hdl64e().with_columns(512),
        )
    }

    #[test]
    fn ideal_scan_has_labels_materials_and_sane_geometry() {
        let sim = small();
        let scan = sim.scan(0);
        assert_eq!((scan.height(), scan.width()), (64, 512));
        let keep = scan.keep_rate();
        assert!(keep > 0.6 && keep < 1.0, "keep rate {keep}");
        let mut classes = std::collections::BTreeSet::new();
        for k in 0..scan.len() {
            if !scan.is_return(k) {
                continue;
            }
            let r = scan.image.range_m[k];
            assert!((1.45..=80.0).contains(&r));
            let p = scan.image.xyz[k];
            assert!(((p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt() - r).abs() < 1e-3);
            assert_ne!(scan.material[k], Material::None);
            assert!(scan.image.intensity[k] >= 0.0 && scan.image.intensity[k] <= 1.0);
            classes.insert(scan.image.label[k] & 0xffff);
        }
        for c in [label::ROAD, label::SIDEWALK] {
            assert!(classes.contains(&c), "missing class {c}: {classes:?}");
        }
        // Sky: top rows lose far more rays than the lower-middle rows (ground).
        let row_keep = |r: usize| (0..512).filter(|&j| scan.is_return(r * 512 + j)).count();
        assert!(
            row_keep(0) < row_keep(40),
            "{} vs {}",
            row_keep(0),
            row_keep(40)
        );
        // The lowest rows see the road close by.
        let near_road = (0..512)
            .filter(|&j| scan.image.label[63 * 512 + j] & 0xffff == label::ROAD)
            .count();
        assert!(near_road > 100, "{near_road}");
    }

    #[test]
    fn scans_are_deterministic_and_the_ego_moves() {
        let sim = small();
        let a = sim.scan(3);
        let b = sim.scan(3);
        assert_eq!(a.image.range_m, b.image.range_m);
        assert_eq!(a.image.label, b.image.label);
        let p0 = sim.sensor_pose(0.0).origin;
        let p1 = sim.sensor_pose(0.5).origin;
        assert!(((p1 - p0).length() - 5.0).abs() < 0.2);
        let q = sim.sensor_pose(0.0).quaternion();
        assert!((q.iter().map(|c| c * c).sum::<f64>() - 1.0).abs() < 1e-9);
    }

    #[test]
    fn per_point_time_covers_one_sweep_starting_ahead() {
        let t = SweepTiming::default();
        assert!(t.time_at(0.0).abs() < 1e-6);
        assert!((t.time_at(std::f32::consts::FRAC_PI_2) - 0.025).abs() < 1e-6);
        assert!((t.time_at(-0.001) - 0.1).abs() < 1e-4);
    }

    #[test]
    fn organized_and_unorganized_clouds_agree() {
        let scan = small().scan(0);
        let org = scan.to_scan(true);
        let un = scan.to_scan(false);
        assert_eq!((org.height, org.width), (64, 512));
        assert_eq!(org.returns(), un.len());
        assert_eq!(un.returns(), un.len());
        let rings = un.ring.as_ref().unwrap();
        assert!(rings.windows(2).all(|w| w[0] <= w[1]));
    }
}
