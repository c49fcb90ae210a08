//! How far a sensor's scans are from what the decoding model saw (KITTI HDL-64E outdoors:
//! elevations of [`super::model_grid`], ranges 1.45-80 m), so a user decoding, say, an
//! indoor Ouster scan is told what the decoded channels are worth there.

use crate::lidar::Scan;
use crate::model::data::{MAX_DEPTH_M, MIN_DEPTH_M};

/// Returns of a scan inside the model's view, with the scan's own spans (5th-95th
/// percentiles).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ModelFit {
    pub inside_fraction: f64,
    pub elevation_deg: (f32, f32),
    pub range_m: (f32, f32),
    pub model_elevation_deg: (f32, f32),
}

/// Below this fraction of returns inside the model's view, a warning is due.
pub const WARN_BELOW: f64 = 0.7;

fn percentiles(mut v: Vec<f32>) -> (f32, f32) {
    v.sort_by(f32::total_cmp);
    let at = |q: f64| v[((v.len() - 1) as f64 * q).round() as usize];
    (at(0.05), at(0.95))
}

/// `None` for a scan without returns.
pub fn model_fit(scan: &Scan) -> Option<ModelFit> {
    let grid = super::model_grid();
    let (lo, hi) = grid
        .elevation_rad
        .iter()
        .fold((f32::MAX, f32::MIN), |(a, b), &e| (a.min(e), b.max(e)));
    // Half a beam spacing of margin around the model's outermost beams.
    let margin = (hi - lo) / (grid.height.max(2) - 1) as f32 / 2.0;
    let (mut elevations, mut ranges, mut inside) = (Vec::new(), Vec::new(), 0usize);
    for &[x, y, z] in &scan.xyz {
        let r = (x * x + y * y + z * z).sqrt();
        if !(r > 0.0 && r.is_finite()) {
            continue;
        }
        let e = z.atan2(x.hypot(y));
        inside += usize::from(
            e >= lo - margin && e <= hi + margin && (MIN_DEPTH_M..=MAX_DEPTH_M).contains(&r),
        );
        elevations.push(e.to_degrees());
        ranges.push(r);
    }
    if ranges.is_empty() {
        return None;
    }
    Some(ModelFit {
        inside_fraction: inside as f64 / ranges.len() as f64,
        elevation_deg: percentiles(elevations),
        range_m: percentiles(ranges),
        model_elevation_deg: (lo.to_degrees(), hi.to_degrees()),
    })
}

impl ModelFit {
    /// The warning for a topic whose scans are mostly outside the model's view.
    pub fn warning(&self, sensor: &str) -> Option<String> {
        (self.inside_fraction < WARN_BELOW).then(|| {
            format!(
                "its sensor ({sensor}: elevations {:.0} to {:.0} deg, ranges {:.1}-{:.1} m) is far from the decoding model's (KITTI HDL-64E: {:.0} to {:.0} deg, {MIN_DEPTH_M}-{MAX_DEPTH_M} m): only {:.0} % of returns are where the model has learnt scenes, so `depth`, `raydrop_prob`, `raydrop_mask` and `points` are guesses elsewhere (the rest of the image is filled from an outdoor-driving prior); `range` is exact",
                self.elevation_deg.0,
                self.elevation_deg.1,
                self.range_m.0,
                self.range_m.1,
                self.model_elevation_deg.0,
                self.model_elevation_deg.1,
                100.0 * self.inside_fraction
            )
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lidar::SensorProfile;

    /// A scan of `profile` with every ray returning at `range(k)`.
    fn scan(profile: &str, range: impl Fn(usize) -> f32) -> Scan {
        let grid = SensorProfile::resolve(profile)
            .unwrap()
            .with_columns(256)
            .angle_grid();
        let xyz = (0..grid.len())
            .map(|k| grid.direction(k).map(|c| c * range(k)))
            .collect();
        Scan {
            xyz,
            ..Default::default()
        }
    }

    #[test]
    fn an_indoor_ouster_scan_is_flagged_and_a_kitti_street_is_not() {
        let street = model_fit(&scan("hdl64e", |k| 5.0 + (k % 50) as f32)).unwrap();
        assert!(street.inside_fraction > 0.95, "{street:?}");
        assert!(street.warning("hdl64e").is_none());
        // OS1-64 at +-16 deg in a room: 0.6-15 m.
        let room = model_fit(&scan("os1-64", |k| 0.6 + (k % 30) as f32 * 0.5)).unwrap();
        assert!(room.inside_fraction < WARN_BELOW, "{room:?}");
        let w = room.warning("os1-64").unwrap();
        assert!(
            w.contains("os1-64") && w.contains("`range` is exact"),
            "{w}"
        );
        assert!(model_fit(&Scan::default()).is_none());
    }
}
