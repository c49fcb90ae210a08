//! The two-parameter curve families: `range_dropout` (log-logistic in the completed
//! range) and `incidence_dropout` (log-logistic in cos(incidence)), the physics
//! module's own curves fitted by grid search.

use serde_json::{Map, Value, json};

use super::{fit_curve, round3};
use crate::diagnose::fit::{DropFamily, DropFit, Pixels, QTable};
use crate::lidar::edges::MAX_EDGE_PX;
use crate::physics::dropout::{IncidenceDropout, RangeDropout};
use crate::physics::{Effect, RayFeatures};
use crate::sim::Material;

fn ray(range_m: f32, incidence_rad: f32) -> RayFeatures {
    RayFeatures {
        row: 0,
        column: 0,
        range_m,
        incidence_rad,
        material: Material::Concrete,
        class: 0,
        reflectivity: 0.5,
        intensity: 0.5,
        azimuth_rad: 0.0,
        elevation_rad: 0.0,
        edge_px: MAX_EDGE_PX,
    }
}

const SOFTNESS: [f32; 9] = [0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5, 0.7, 1.0];

/// `range_dropout`: drop rate rising with the completed range.
pub struct RangeFamily;
const RANGE_BIN_M: f32 = 1.0;
const RANGE_BINS: usize = 150;
/// A dropped pixel counts for the range curve when returns enclose it within
/// this many pixels (`Pixels::enclosure_px`).
const RANGE_ENCLOSURE_PX: u8 = crate::diagnose::fit::ENCLOSED_PX;

impl DropFamily for RangeFamily {
    fn id(&self) -> &'static str {
        "range_dropout"
    }
    fn bins(&self, _: &Pixels) -> usize {
        RANGE_BINS
    }
    /// Dropped pixels count only when returns enclose them closely, or they lie on
    /// a level plane (the open ground within reach, a garage's ceiling): the range an
    /// open-space pixel takes from an object's outline is the scene's, not the sensor's.
    fn bin(&self, px: &Pixels, i: usize) -> Option<usize> {
        let r = px.range_m[i];
        let level_plane = px.level_plane.get(i).copied().unwrap_or(false);
        (r.is_finite() && (px.enclosure_px[i] <= RANGE_ENCLOSURE_PX || level_plane))
            .then(|| ((r.max(0.0) / RANGE_BIN_M) as usize).min(RANGE_BINS - 1))
    }
    fn fit(&self, table: &QTable, _: &Pixels) -> Option<DropFit> {
        let grid_a: Vec<f32> = (0..40).map(|i| 5.0 * 60f32.powf(i as f32 / 39.0)).collect();
        let probs = |a: f32, b: f32| {
            let e = RangeDropout {
                enabled: true,
                range_50_m: a,
                softness: b,
            };
            (0..RANGE_BINS)
                .map(|bin| f64::from(e.drop_prob(&ray((bin as f32 + 0.5) * RANGE_BIN_M, 0.0))))
                .collect()
        };
        let (a, b, drop_prob) = fit_curve(table, &grid_a, &SOFTNESS, probs)?;
        // The range where 10 % of the rays drop: p = 0.1 <=> d = r50 · 9^(-s/2).
        let onset = a * 9f32.powf(-b / 2.0);
        Some(curve_fit(
            "range_dropout",
            [("range_50_m", a), ("softness", b)],
            drop_prob,
            format!("ranges beyond ~{onset:.0} m (10 % of rays lost there, half at {a:.0} m)"),
        ))
    }
}

/// `incidence_dropout`: drop rate rising as cos(incidence) falls.
pub struct IncidenceFamily;
const COS_BINS: usize = 50;

impl DropFamily for IncidenceFamily {
    fn id(&self) -> &'static str {
        "incidence_dropout"
    }
    fn bins(&self, _: &Pixels) -> usize {
        COS_BINS
    }
    /// Normals beyond ~89 deg (cos < 0.02) come from fill and edge artefacts
    /// more than from surfaces: left out (unknown).
    fn bin(&self, px: &Pixels, i: usize) -> Option<usize> {
        let c = px.cos_incidence[i];
        (c.is_finite() && c >= 1.0 / COS_BINS as f32)
            .then(|| ((c.min(1.0) * COS_BINS as f32) as usize).min(COS_BINS - 1))
    }
    fn fit(&self, table: &QTable, _: &Pixels) -> Option<DropFit> {
        // cos_50 from 0.03 (88 deg) to 0.6: a curve that only bites in the
        // last bin would fit the normals' artefacts.
        let grid_a: Vec<f32> = (0..40)
            .map(|i| 0.03 * 20f32.powf(i as f32 / 39.0))
            .collect();
        let probs = |a: f32, b: f32| {
            let e = IncidenceDropout {
                enabled: true,
                cos_50: a,
                softness: b,
            };
            (0..COS_BINS)
                .map(|bin| {
                    let cos = (bin as f32 + 0.5) / COS_BINS as f32;
                    f64::from(e.drop_prob(&ray(10.0, cos.acos())))
                })
                .collect()
        };
        let (a, b, drop_prob) = fit_curve(table, &grid_a, &SOFTNESS, probs)?;
        let onset_deg = (a * 9f32.powf(b)).min(1.0).acos().to_degrees();
        Some(curve_fit(
            "incidence_dropout",
            [("cos_50", a), ("softness", b)],
            drop_prob,
            format!(
                "incidence angles above ~{onset_deg:.0} deg (grazing surfaces; half the rays lost at {:.0} deg)",
                a.acos().to_degrees()
            ),
        ))
    }
}

/// The fit of a two-parameter drop curve: its parameters (rounded in the report, exact in
/// the fitted physics), per-bin drop probabilities and location in words.
fn curve_fit(id: &str, values: [(&str, f32); 2], drop_prob: Vec<f64>, location: String) -> DropFit {
    let mut params = Map::new();
    let mut effect = Map::new();
    for (name, v) in values {
        params.insert(name.into(), json!(round3(v.into())));
        effect.insert(name.into(), json!(v));
    }
    let mut physics = Map::new();
    physics.insert(id.into(), Value::Object(effect));
    DropFit {
        drop_prob,
        params,
        physics,
        n_params: 2,
        location,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn range_curve_leaves_out_drops_in_open_space() {
        // A kept pixel, a dropped one enclosed by returns 2 pixels away, and a
        // dropped one completed from an outline with nothing beyond it.
        let px = Pixels {
            range_m: vec![70.0, 70.0, 70.0],
            kept: vec![true, false, false],
            enclosure_px: vec![0, 2, 16],
            ..Default::default()
        };
        let bins: Vec<Option<usize>> = (0..3).map(|i| RangeFamily.bin(&px, i)).collect();
        assert_eq!(bins, [Some(70), Some(70), None]);
    }
}
