//! Whether the two recordings show alike scenes. The diagnosis compares drop rates of an
//! unpaired sim and real recording; where their scenes differ (a simulated street against
//! a real room), a rate that differs by range or incidence may be the scene's, not a missing
//! effect. Measured from the returns alone: their range distributions, the share beyond
//! 20 m, and the share on a level ground plane below the sensor.

use serde::Serialize;

use crate::diagnose::features::ScanFeatures;

/// Width of a range bin of [`SceneContrast::range_distance`], meters.
const RANGE_BIN_M: f32 = 2.0;
/// Returns beyond this are "far".
const FAR_M: f32 = 20.0;
/// Returns at least this far below the horizon can lie on the ground.
const GROUND_BELOW_RAD: f32 = 0.05;
/// A return lies on the ground when its height below the sensor is within this of the
/// recording's median such height.
const GROUND_BAND_M: f32 = 0.3;

/// Past these, the scenes are said to differ.
const MAX_RANGE_DISTANCE: f64 = 0.4;
const MAX_SHARE_GAP: f64 = 0.3;

/// How far apart the scenes of the sim and real recordings are.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SceneContrast {
    /// Total-variation distance between the range histograms of the returns (2 m bins):
    /// 0 for the same distribution, 1 for disjoint ones.
    pub range_distance: f64,
    /// Share of the returns beyond 20 m.
    pub far_share_sim: f64,
    pub far_share_real: f64,
    /// Share of the returns below the horizon that lie on one level plane (the ground).
    pub ground_share_sim: f64,
    pub ground_share_real: f64,
    /// Whether the scenes differ so much that a named effect may be a scene difference.
    pub differs: bool,
}

/// The ranges of the returns of `scans`, and their heights below the sensor where the ray
/// points below the horizon.
fn returns(scans: &[ScanFeatures]) -> (Vec<f32>, Vec<f32>) {
    let (mut ranges, mut below) = (Vec::new(), Vec::new());
    for f in scans {
        for k in (0..f.len()).filter(|&k| f.kept[k] && f.range_m[k].is_finite()) {
            let r = f.range_m[k];
            ranges.push(r);
            if f.elevation_rad[k] < -GROUND_BELOW_RAD {
                below.push(-r * f.elevation_rad[k].sin());
            }
        }
    }
    (ranges, below)
}

fn histogram(ranges: &[f32], bins: usize) -> Vec<f64> {
    let mut h = vec![0.0; bins];
    for &r in ranges {
        h[((r / RANGE_BIN_M) as usize).min(bins - 1)] += 1.0;
    }
    let n = ranges.len().max(1) as f64;
    h.iter().map(|c| c / n).collect()
}

/// Share of `heights` within [`GROUND_BAND_M`] of their median.
fn ground_share(mut heights: Vec<f32>) -> f64 {
    if heights.is_empty() {
        return 0.0;
    }
    heights.sort_by(f32::total_cmp);
    let median = heights[heights.len() / 2];
    let on = heights
        .iter()
        .filter(|h| (*h - median).abs() <= GROUND_BAND_M)
        .count();
    on as f64 / heights.len() as f64
}

impl SceneContrast {
    pub fn measure(sim: &[ScanFeatures], real: &[ScanFeatures]) -> Self {
        let (r_sim, g_sim) = returns(sim);
        let (r_real, g_real) = returns(real);
        let top = r_sim.iter().chain(&r_real).fold(0.0f32, |a, &r| a.max(r));
        let bins = ((top / RANGE_BIN_M) as usize + 1).clamp(1, 10_000);
        let (h_sim, h_real) = (histogram(&r_sim, bins), histogram(&r_real, bins));
        let range_distance = 0.5
            * h_sim
                .iter()
                .zip(&h_real)
                .map(|(a, b)| (a - b).abs())
                .sum::<f64>();
        let far =
            |r: &[f32]| r.iter().filter(|&&x| x > FAR_M).count() as f64 / r.len().max(1) as f64;
        let (far_share_sim, far_share_real) = (far(&r_sim), far(&r_real));
        let (ground_share_sim, ground_share_real) = (ground_share(g_sim), ground_share(g_real));
        let differs = range_distance > MAX_RANGE_DISTANCE
            || (far_share_sim - far_share_real).abs() > MAX_SHARE_GAP
            || (ground_share_sim - ground_share_real).abs() > MAX_SHARE_GAP;
        SceneContrast {
            range_distance,
            far_share_sim,
            far_share_real,
            ground_share_sim,
            ground_share_real,
            differs,
        }
    }

    /// One sentence for the report's first screen.
    pub fn sentence(&self) -> String {
        let pct = |v: f64| format!("{:.0} %", 100.0 * v);
        format!(
            "the two recordings' scenes {}: their range distributions are {:.2} apart (0 = alike, 1 = disjoint), {} of the sim's returns and {} of the real ones lie beyond 20 m, and {} against {} of the returns below the horizon lie on a level ground{}",
            if self.differs { "differ" } else { "are alike" },
            self.range_distance,
            pct(self.far_share_sim),
            pct(self.far_share_real),
            pct(self.ground_share_sim),
            pct(self.ground_share_real),
            if self.differs {
                "; the effects named may be scene differences, and their confidence is halved"
            } else {
                ""
            }
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Scans of `rows` x 64 pixels at elevations -0.2..0.2 rad, every return at `range(row)`.
    fn scans(range: impl Fn(usize) -> f32) -> Vec<ScanFeatures> {
        let (h, w) = (16, 64);
        let mut f = ScanFeatures::empty(h, w);
        for k in 0..h * w {
            let row = k / w;
            f.row.push(row as u32);
            f.elevation_rad
                .push(0.2 - 0.4 * row as f32 / (h - 1) as f32);
            f.azimuth_rad.push(k as f32);
            f.range_m.push(range(row));
            f.incidence_rad.push(0.5);
            f.edge_px.push(8);
            f.row_edge_px.push(8);
            f.class.push(0);
            f.kept.push(true);
        }
        vec![f]
    }

    #[test]
    fn alike_scenes_are_alike_and_a_room_is_not_a_street() {
        // A street: the ground below the horizon (1.7 m down), far returns above it.
        let street = |row: usize| {
            let e = 0.2 - 0.4 * row as f32 / 15.0;
            if e < -0.05 { 1.7 / -e.sin() } else { 40.0 }
        };
        let room = |_: usize| 4.0;
        let same = SceneContrast::measure(&scans(street), &scans(street));
        assert!(!same.differs && same.range_distance < 1e-9, "{same:?}");
        let apart = SceneContrast::measure(&scans(street), &scans(room));
        assert!(apart.differs, "{apart:?}");
        assert!(
            apart.range_distance > 0.9 && apart.far_share_sim > 0.3 && apart.far_share_real == 0.0
        );
        assert!(apart.sentence().contains("differ"));
    }
}
