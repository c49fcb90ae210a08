//! Level planes that dropped pixels may lie on: the open ground within reach and a
//! level ceiling (a garage, a tunnel), found from the scans' returns, and the range
//! at which each dropped pixel's ray meets them.

use super::enclosure::ENCLOSED_PX;
use crate::diagnose::features::ScanFeatures;

/// Elevation above which a pixel without geometry may be open space rather than
/// a dropped ray: where a level ground `h` below the sensor lies beyond
/// `GROUND_REACH_FRACTION` of the reach, `h` the median height of the bottom
/// row's returns below the sensor. Whether a scene has sky or open space there
/// is not physics, whatever the sensor's field of view; below it the ground is
/// within reach, so a pixel without a return there lost its ray. Without a
/// usable ground estimate: the horizon (elevation 0).
/// `ground_m` is [`ground_depth_m`] of the scans, None where it or the reach is unknown.
pub(super) fn open_elevation_rad(ground_m: Option<f32>, reach_m: f32) -> f32 {
    const GROUND_REACH_FRACTION: f32 = 0.8;
    ground_m.map_or(0.0, |h| {
        -(h / (GROUND_REACH_FRACTION * reach_m))
            .clamp(0.0, 1.0)
            .asin()
    })
}

/// For each pixel of a scan on the open ground within reach, the level ground's range
/// `h / sin(-e)` (else NaN): dropped, not enclosed by returns (the fill copied some
/// outline's range into it), below `open_above` (the ground lies within reach there),
/// its ground point beyond every return of its column (nearer, the ground was in
/// sight: an object lost its rays, and the feature fill completes it), and no return
/// above it standing nearer than that ground point (a wall it would hit first).
/// A column whose returns all lie in the near field qualifies too: where grazing
/// incidence empties the ground from a few metres on (a low-resolution sensor's
/// ground rows), that is all a column keeps.
pub(super) fn open_ground_range(
    f: &ScanFeatures,
    enclosure: &[u8],
    open_above: f32,
    h: f32,
) -> Vec<f32> {
    let w = f.width.max(1);
    let mut out = vec![f32::NAN; f.len()];
    for j in 0..w {
        let column = (j..f.len()).step_by(w);
        let farthest_m = column
            .clone()
            .filter(|&k| f.kept[k])
            .map(|k| f.range_m[k] * f.elevation_rad[k].cos())
            .fold(0.0f32, f32::max);
        // Horizontal distance of the nearest return above, walking down the column.
        let mut wall_m = f32::INFINITY;
        for k in column {
            let e = f.elevation_rad[k];
            if f.kept[k] {
                wall_m = f.range_m[k] * e.cos();
                continue;
            }
            if enclosure[k] <= ENCLOSED_PX || e > open_above || e >= 0.0 {
                continue;
            }
            let ground_r = h / (-e).sin();
            let ground_m = ground_r * e.cos();
            if ground_m > farthest_m && ground_m <= wall_m {
                out[k] = ground_r;
            }
        }
    }
    out
}

/// The ground's depth below the sensor: the median over the bottom row's returns
/// below it (None with fewer than 20).
pub(super) fn ground_depth_m(scans: &[ScanFeatures]) -> Option<f32> {
    let mut heights: Vec<f32> = scans
        .iter()
        .flat_map(|f| {
            let bottom = f.len().saturating_sub(f.width);
            (bottom..f.len())
                .filter(|&k| f.kept[k] && f.elevation_rad[k] < 0.0)
                .map(|k| -f.range_m[k] * f.elevation_rad[k].sin())
        })
        .filter(|h| h.is_finite() && *h > 0.2)
        .collect();
    if heights.len() < 20 {
        return None;
    }
    let mid = heights.len() / 2;
    Some(*heights.select_nth_unstable_by(mid, f32::total_cmp).1)
}

/// Upward returns a ceiling estimate needs, over all scans.
const CEILING_MIN_RETURNS: usize = 200;
/// Share of the upward returns that must lie on the estimated ceiling.
const CEILING_SHARE: f32 = 0.4;

/// The height above the sensor of a level ceiling that covers the scans (a garage,
/// a tunnel): the 95th percentile of the upward returns' heights, where at least
/// [`CEILING_SHARE`] of them lie within 5 % of it. None in the open, where trees and
/// buildings spread the heights.
pub(super) fn ceiling_height_m(scans: &[ScanFeatures]) -> Option<f32> {
    let min_elevation = 0.5f32.to_radians();
    let mut heights: Vec<f32> = scans
        .iter()
        .flat_map(|f| {
            (0..f.len())
                .filter(|&k| f.kept[k] && f.elevation_rad[k] > min_elevation)
                .map(|k| f.range_m[k] * f.elevation_rad[k].sin())
        })
        .filter(|h| h.is_finite() && *h > 0.2)
        .collect();
    if heights.len() < CEILING_MIN_RETURNS {
        return None;
    }
    let i = (heights.len() - 1) * 95 / 100;
    let h = *heights.select_nth_unstable_by(i, f32::total_cmp).1;
    let on = heights
        .iter()
        .filter(|&&z| (z - h).abs() <= 0.05 * h)
        .count();
    (on as f32 >= CEILING_SHARE * heights.len() as f32).then_some(h)
}

/// For each dropped upward pixel of a scan whose ray meets the level ceiling `h`
/// above the sensor within reach, the ceiling's range `h / sin(e)` (else NaN), unless
/// the nearest return below it in its column (a wall or a pillar, walking up from
/// the horizon) stands nearer than that ceiling point: the ray would hit it first.
/// Where grazing drops empty the far ceiling, the rows between the wall tops and the
/// near ceiling hold no return to complete them from.
pub(super) fn ceiling_range(f: &ScanFeatures, h: f32, reach_m: f32) -> Vec<f32> {
    let w = f.width.max(1);
    let mut out = vec![f32::NAN; f.len()];
    for j in 0..w {
        let mut below_m = f32::INFINITY;
        for k in (j..f.len()).step_by(w).rev() {
            let e = f.elevation_rad[k];
            if e <= 0.0 {
                continue;
            }
            if f.kept[k] {
                below_m = f.range_m[k] * e.cos();
                continue;
            }
            let range_m = h / e.sin();
            if h / e.tan() < below_m && range_m <= reach_m {
                out[k] = range_m;
            }
        }
    }
    out
}
