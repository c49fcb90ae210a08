//! A real scan as a simulated one, so that catalogue effects can act on real data: true
//! range and labels are the measured ones, incidence comes from the scan's own features.

use crate::diagnose::features::{FeatureOptions, ScanFeatures};
use crate::lidar::{RangeImage, SensorProfile};
use crate::sim::geometry::v3;
use crate::sim::material::typical_material;
use crate::sim::{Material, SensorPose, SimScan, SweepTiming};

/// A projected scan as a [`SimScan`] the physics can act on: true range and label
/// = the measured ones, incidence from the completed normals, time from the
/// sweep, the ego moving straight ahead at `speed_mps`.
pub fn as_sim_scan(
    image: RangeImage,
    index: u32,
    profile: &SensorProfile,
    speed_mps: f32,
) -> SimScan {
    let f = ScanFeatures::from_image(&image, &FeatureOptions::default());
    let n = image.len();
    let timing = SweepTiming::default();
    let class: Vec<u32> = image.label.iter().map(|l| l & 0xffff).collect();
    SimScan {
        material: (0..n)
            .map(|k| {
                if image.range_m[k] > 0.0 {
                    typical_material(class[k])
                } else {
                    Material::None
                }
            })
            .collect(),
        incidence_rad: f
            .incidence_rad
            .iter()
            .map(|a| if a.is_finite() { *a } else { 0.0 })
            .collect(),
        normal: f.normal,
        reflectivity: image.intensity.iter().map(|i| i.clamp(0.0, 1.0)).collect(),
        time_s: image
            .angles
            .azimuth_rad
            .iter()
            .map(|a| timing.time_at(*a))
            .collect(),
        true_range_m: image.range_m.clone(),
        true_label: image.label.clone(),
        index,
        start_time_s: 0.1 * f64::from(index),
        pose: SensorPose {
            origin: v3(0.0, 0.0, 0.0),
            axes: [v3(1.0, 0.0, 0.0), v3(0.0, 1.0, 0.0), v3(0.0, 0.0, 1.0)],
            velocity_mps: [speed_mps, 0.0, 0.0],
            yaw_rate_rps: 0.0,
            yaw_rad: 0.0,
        },
        min_range_m: profile.min_range_m,
        max_range_m: profile.max_range_m,
        image,
    }
}
