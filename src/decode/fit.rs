//! How far a sensor's scans are from what the decoding model saw (the sensor it was trained
//! for: its beams' elevations and valid range; the shipped model's is KITTI's HDL-64E, 1.45-80
//! m), so a user decoding, say, an indoor Ouster scan through a street model is told what the
//! decoded channels are worth there, and gets prior-free channels unless forced.

use crate::lidar::{Scan, SensorProfile};

/// Returns of a scan inside the model's view, with the scan's range span (5th-95th
/// percentiles), and the sensor's beams outside it.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelFit {
    pub inside_fraction: f64,
    /// The sensor's top and bottom beams, degrees (its beam table).
    pub beam_elevation_deg: (f32, f32),
    /// Beams of the sensor above or below the model's outermost beams (by more than half a
    /// model beam spacing): their rows are not decoded from what the model learnt.
    pub beams_outside: usize,
    pub beams: usize,
    pub range_m: (f32, f32),
    /// The model's top and bottom beams, degrees.
    pub model_elevation_deg: (f32, f32),
    /// The model's sensor: its name and valid range.
    pub model_sensor: String,
    pub model_range_m: (f32, f32),
}

/// Below this fraction of returns inside the model's view, a warning is due...
pub const WARN_BELOW: f64 = 0.7;
/// ...and above this fraction of the sensor's beams outside it.
pub const WARN_BEAMS_OUTSIDE: f64 = 0.1;

fn percentiles(mut v: Vec<f32>) -> (f32, f32) {
    v.sort_by(f32::total_cmp);
    let at = |q: f64| v[((v.len() - 1) as f64 * q).round() as usize];
    (at(0.05), at(0.95))
}

/// How `scan` of a sensor with `profile` fits the view of a model trained for `model`;
/// `None` for a scan without returns.
pub fn model_fit(scan: &Scan, profile: &SensorProfile, model: &SensorProfile) -> Option<ModelFit> {
    let (lo, hi) = model
        .elevation_deg
        .iter()
        .fold((f32::MAX, f32::MIN), |(a, b), &e| (a.min(e), b.max(e)));
    let (lo, hi) = (lo.to_radians(), hi.to_radians());
    // Half a beam spacing of margin around the model's outermost beams.
    let margin = (hi - lo) / (model.beams().max(2) - 1) as f32 / 2.0;
    let valid = model.min_range_m..=model.max_range_m;
    let within = |e: f32| e >= lo - margin && e <= hi + margin;
    let (mut ranges, mut inside) = (Vec::new(), 0usize);
    for &[x, y, z] in &scan.xyz {
        let r = (x * x + y * y + z * z).sqrt();
        if !(r > 0.0 && r.is_finite()) {
            continue;
        }
        let e = z.atan2(x.hypot(y));
        inside += usize::from(within(e) && valid.contains(&r));
        ranges.push(r);
    }
    if ranges.is_empty() {
        return None;
    }
    let beams = &profile.elevation_deg;
    let (top, bottom) = beams
        .iter()
        .fold((f32::MIN, f32::MAX), |(t, b), &e| (t.max(e), b.min(e)));
    Some(ModelFit {
        inside_fraction: inside as f64 / ranges.len() as f64,
        beam_elevation_deg: (top, bottom),
        beams_outside: beams.iter().filter(|e| !within(e.to_radians())).count(),
        beams: beams.len(),
        range_m: percentiles(ranges),
        model_elevation_deg: (hi.to_degrees(), lo.to_degrees()),
        model_sensor: model.name.clone(),
        model_range_m: (model.min_range_m, model.max_range_m),
    })
}

impl ModelFit {
    /// Whether the model covers this sensor: at most [`WARN_BEAMS_OUTSIDE`] of its beams
    /// outside the model's view (an estimated beam table is off by a degree or two at its
    /// ends) and at least [`WARN_BELOW`] of the returns inside it. Where it does not,
    /// `convert` writes prior-free channels unless a model is forced (`--model`).
    pub fn covers(&self) -> bool {
        let beams_out = self.beams_outside as f64 > WARN_BEAMS_OUTSIDE * self.beams as f64;
        self.inside_fraction >= WARN_BELOW && !beams_out
    }

    /// What a user is told about a topic the model does not cover: its channels are
    /// prior-free, and how to get a prior for the sensor.
    pub fn prior_free_note(&self, sensor: &str) -> String {
        format!(
            "no decoding model covers its sensor ({sensor}: beams {:+.1} to {:+.1} deg, ranges {:.1}-{:.1} m; the model's: {}, {:+.1} to {:+.1} deg, {}-{} m; {} of its {} beams outside, {:.0} % of returns inside), so its channels are prior-free on the sensor's own grid: `depth` is the edge-aware completion of the measured returns, `raydrop_prob` and the masks the recording's own drop rates (each scan's fitted on its other scans), and no `x_d` is written. Train a prior for this sensor on its recordings (`rangegan-mcap train RUN --data RECORDINGS`, then --model RUN), or decode through a model anyway with --model",
            self.beam_elevation_deg.0,
            self.beam_elevation_deg.1,
            self.range_m.0,
            self.range_m.1,
            self.model_sensor,
            self.model_elevation_deg.0,
            self.model_elevation_deg.1,
            self.model_range_m.0,
            self.model_range_m.1,
            self.beams_outside,
            self.beams,
            100.0 * self.inside_fraction
        )
    }

    /// The warning for a topic whose scans are mostly outside the model's view, or whose
    /// sensor has beams outside it.
    pub fn warning(&self, sensor: &str) -> Option<String> {
        (!self.covers()).then(|| {
            format!(
                "its sensor ({sensor}: beams {:+.1} to {:+.1} deg, ranges {:.1}-{:.1} m) is far from the decoding model's ({}: {:+.1} to {:+.1} deg, {}-{} m): {} of its {} beams lie outside the model's view and only {:.0} % of returns are where the model has learnt scenes, so `depth`, `raydrop_prob`, `raydrop_mask` and `points` are guesses elsewhere (the rest of the image is filled from an outdoor-driving prior); `range` is exact",
                self.beam_elevation_deg.0,
                self.beam_elevation_deg.1,
                self.range_m.0,
                self.range_m.1,
                self.model_sensor,
                self.model_elevation_deg.0,
                self.model_elevation_deg.1,
                self.model_range_m.0,
                self.model_range_m.1,
                self.beams_outside,
                self.beams,
                100.0 * self.inside_fraction
            )
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lidar::SensorProfile;

    fn kitti() -> SensorProfile {
        crate::model::config::default_sensor()
    }

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
        let hdl = SensorProfile::builtin("hdl64e").unwrap();
        let street = model_fit(&scan("hdl64e", |k| 5.0 + (k % 50) as f32), &hdl, &kitti()).unwrap();
        assert!(street.inside_fraction > 0.95, "{street:?}");
        assert_eq!(street.beams_outside, 0);
        assert!(street.warning("hdl64e").is_none());
        // OS1-64 at +-22.5 deg in a room: 0.6-15 m.
        let os1 = SensorProfile::builtin("os1-64").unwrap();
        let room = model_fit(
            &scan("os1-64", |k| 0.6 + (k % 30) as f32 * 0.5),
            &os1,
            &kitti(),
        )
        .unwrap();
        assert!(room.inside_fraction < WARN_BELOW, "{room:?}");
        let w = room.warning("os1-64").unwrap();
        assert!(
            w.contains("os1-64") && w.contains("`range` is exact") && w.contains("+22.5 to -22.5"),
            "{w}"
        );
        assert!(model_fit(&Scan::default(), &os1, &kitti()).is_none());
        // A model trained for the OS1-64 covers the same room.
        let own = model_fit(&scan("os1-64", |k| 0.6 + (k % 30) as f32 * 0.5), &os1, &os1).unwrap();
        assert!(own.covers() && own.inside_fraction > 0.99, "{own:?}");
    }

    /// A VLP-32C outdoors keeps most returns inside the model's view, but its beams reach
    /// +15 deg, far above the HDL-64E's +2 deg: the warning says so by its beams.
    #[test]
    fn beams_outside_the_model_warn_even_where_most_returns_are_inside() {
        let vlp = SensorProfile::builtin("vlp32c").unwrap();
        let grid = vlp.clone().with_columns(256).angle_grid();
        // Returns on the rows inside the model's view only (the sky above gives none).
        let xyz = (0..grid.len())
            .filter(|&k| grid.elevation_rad[k].to_degrees() < 3.0)
            .map(|k| grid.direction(k).map(|c| c * 12.0))
            .collect();
        let fit = model_fit(&Scan::from_xyz(xyz), &vlp, &kitti()).unwrap();
        assert!(fit.inside_fraction >= WARN_BELOW, "{fit:?}");
        assert!(
            fit.beams_outside as f64 > WARN_BEAMS_OUTSIDE * 32.0,
            "{fit:?}"
        );
        let w = fit.warning("vlp32c").unwrap();
        assert!(w.contains("of its 32 beams lie outside"), "{w}");
    }
}
