//! The interpolation prior: what a scan's own returns say of every ray by linear interpolation
//! along its beam (row) and along its column.
//!
//! The renderer outputs depth as a correction of this prior ([`base_log_depth`]), so a model
//! starts where the simple baseline it must beat is, and learns what interpolation gets wrong:
//! edges, occlusions, surfaces that end, sky. Both the encoder and the renderer see the prior
//! together with how far each interpolation had to reach, since a line across two columns is
//! worth more than one across a sector.

use super::render::{LN_MID_DEPTH, LOG_DEPTH_SPAN};
use super::{Ray, SpatialConfig};
use crate::lidar::AngleGrid;

/// Values per ray: along the row and along the column each the normalised log range of the
/// interpolation, how far it reached ([`reach_feature`]) and whether there was one.
pub const PRIOR_FEATURES: usize = 6;

/// The angle (radians) that scales reach: about one column of a 2 048-column turn.
const REACH_SCALE_RAD: f32 = 0.003;
/// Reach features are divided by this, so a whole turn reads about 1.3.
const REACH_NORM: f32 = 6.0;

/// A reach (the angle between the two returns a ray is interpolated between, or twice the
/// distance to the only one) as a feature that tells one column from a few degrees from a
/// sector.
fn reach_feature(reach_rad: f32) -> f32 {
    (1.0 + reach_rad / REACH_SCALE_RAD).ln() / REACH_NORM
}

/// The reach feature of a ray with nothing to interpolate from (a whole turn's reach).
fn no_reach() -> f32 {
    reach_feature(std::f32::consts::TAU)
}

/// One interpolation of a ray: range (m) and reach (rad); `None` where its line has no return.
pub type Line = Option<(f32, f32)>;

/// The prior of every ray of an observation, `[H W, PRIOR_FEATURES]` row-major. Returns
/// interpolate to themselves (reach 0); drops and unknown rays are interpolated over. Rows
/// wrap around when the grid is a whole turn (`circular`).
pub fn prior(rays: &[Ray], angles: &AngleGrid, circular: bool, config: &SpatialConfig) -> Vec<f32> {
    let (h, w) = (angles.height, angles.width);
    let range: Vec<f32> = rays
        .iter()
        .map(|r| match *r {
            Ray::Return(r) if r >= config.min_range_m && r <= config.max_range_m => r,
            _ => 0.0,
        })
        .collect();
    let column_step = column_step(angles);
    let along_rows = interpolate(&range, (h, w), true, circular, |_, a, b| {
        (b - a) as f32 * column_step
    });
    let along_columns = interpolate(&range, (h, w), false, false, |col, a, b| {
        (angles.elevation_rad[a as usize * w + col] - angles.elevation_rad[b as usize * w + col])
            .abs()
    });
    let mut out = Vec::with_capacity(h * w * PRIOR_FEATURES);
    for (r, c) in along_rows.into_iter().zip(along_columns) {
        for line in [r, c] {
            match line {
                Some((range, reach)) => {
                    out.extend([normalised_log(range), reach_feature(reach), 1.0])
                }
                None => out.extend([0.0, no_reach(), 0.0]),
            }
        }
    }
    out
}

/// ln(range) on the scale the model reads ranges at.
pub fn normalised_log(range_m: f32) -> f32 {
    (range_m.ln() - LN_MID_DEPTH) / LOG_DEPTH_SPAN
}

/// The log depth (ln m) the renderer corrects: the two interpolations weighted by the inverse
/// of their reach (a return is its own range), the middle of the range where there is none.
pub fn base_log_depth(prior: &[f32]) -> f32 {
    let mut sum = 0.0;
    let mut weight = 0.0;
    for line in prior.chunks_exact(3).take(2) {
        if line[2] > 0.0 {
            let reach = (line[1] * REACH_NORM).exp() - 1.0; // in units of REACH_SCALE_RAD
            let w = 1.0 / reach.max(1e-3);
            sum += w * line[0];
            weight += w;
        }
    }
    let normalised = if weight > 0.0 { sum / weight } else { 0.0 };
    LN_MID_DEPTH + LOG_DEPTH_SPAN * normalised
}

/// The azimuth between neighbouring columns: the median over the first row's steps (a crop
/// keeps its turn's step).
fn column_step(angles: &AngleGrid) -> f32 {
    let w = angles.width;
    if w < 2 {
        return std::f32::consts::TAU;
    }
    let mut steps: Vec<f32> = angles.azimuth_rad[..w]
        .windows(2)
        .map(|p| {
            let d = (p[1] - p[0]).rem_euclid(std::f32::consts::TAU);
            d.min(std::f32::consts::TAU - d)
        })
        .collect();
    steps.sort_by(f32::total_cmp);
    steps[steps.len() / 2].max(1e-6)
}

/// Each pixel of `range` (0 = none) on a line between the nearest returns before and after it
/// along rows (`along_rows`, wrapping when `circular`) or columns, with the reach that
/// `reach(line, a, b)` gives for positions a < b; the one neighbour (reach doubled) where there
/// is only one.
pub fn interpolate(
    range: &[f32],
    (h, w): (usize, usize),
    along_rows: bool,
    circular: bool,
    reach: impl Fn(usize, isize, isize) -> f32,
) -> Vec<Line> {
    let mut out = vec![None; h * w];
    let (lines, len) = if along_rows { (h, w) } else { (w, h) };
    let at = |line: usize, t: usize| {
        if along_rows {
            line * w + t
        } else {
            t * w + line
        }
    };
    let mut hits = Vec::with_capacity(len);
    for line in 0..lines {
        hits.clear();
        hits.extend(
            (0..len)
                .filter(|&t| range[at(line, t)] > 0.0)
                .map(|t| t as isize),
        );
        if hits.is_empty() {
            continue;
        }
        let n = len as isize;
        let value = |x: isize| range[at(line, x.rem_euclid(n) as usize)];
        let reach_of = |a: isize, b: isize| reach(line, a, b);
        let mut after = 0;
        for t in 0..len as isize {
            while after < hits.len() && hits[after] < t {
                after += 1;
            }
            if hits.get(after) == Some(&t) {
                out[at(line, t as usize)] = Some((value(t), 0.0));
                continue;
            }
            let before = after.checked_sub(1).map(|b| hits[b]);
            let next = hits.get(after).copied();
            let (before, next) = match (before, next) {
                (Some(a), None) if circular => (Some(a), Some(hits[0] + n)),
                (None, Some(b)) if circular => (Some(hits[hits.len() - 1] - n), Some(b)),
                other => other,
            };
            out[at(line, t as usize)] = match (before, next) {
                (Some(a), Some(b)) => {
                    let f = (t - a) as f32 / (b - a) as f32;
                    let r = value(a) * (1.0 - f) + value(b) * f;
                    Some((r, reach_of(a, b)))
                }
                (Some(a), None) => Some((value(a), 2.0 * reach_of(a, t))),
                (None, Some(b)) => Some((value(b), 2.0 * reach_of(t, b))),
                (None, None) => None,
            };
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lidar::SensorProfile;

    fn feature(prior: &[f32], k: usize) -> &[f32] {
        &prior[k * PRIOR_FEATURES..(k + 1) * PRIOR_FEATURES]
    }

    #[test]
    fn gaps_take_the_line_between_their_neighbours_and_the_shorter_reach_weighs_more() {
        let angles = SensorProfile::builtin("vlp16")
            .expect("vlp16")
            .with_columns(64)
            .angle_grid();
        let (h, w) = (angles.height, angles.width);
        let config = SpatialConfig::new();
        let mut rays = vec![Ray::Return(10.0); h * w];
        // Row 5: a gap of three columns between 10 m and 20 m; column 9 returns 20 m below.
        rays[5 * w + 9] = Ray::Return(20.0);
        for j in 6..9 {
            rays[5 * w + j] = Ray::Dropped;
        }
        rays[6 * w + 7] = Ray::Return(30.0);
        let features = prior(&rays, &angles, true, &config);
        let f = feature(&features, 5 * w + 7);
        // Two of four columns along: 10 + (20 - 10) / 2.
        assert!((f[0] - normalised_log(15.0)).abs() < 1e-5, "{f:?}");
        assert_eq!(f[2], 1.0);
        // Along the column: 10 m above, 30 m below, half way.
        assert!((f[3] - normalised_log(20.0)).abs() < 1e-5, "{f:?}");
        // The row reaches 4 columns (22.5 deg), the column 2 beams (4 deg): the column weighs
        // more, so the base lies nearer 20 m than 15 m.
        let base = base_log_depth(f).exp();
        assert!(base > 17.5 && base < 20.0, "{base}");
        // A return is its own prior.
        let own = feature(&features, 0);
        assert!((base_log_depth(own).exp() - 10.0).abs() < 1e-3);
        assert_eq!(own[1], 0.0);
        // Nothing returned: no line, the middle of the range.
        let none = prior(&vec![Ray::Unknown; h * w], &angles, true, &config);
        assert!(none.chunks(3).all(|line| line[2] == 0.0));
        assert_eq!(base_log_depth(feature(&none, 3)), LN_MID_DEPTH);
    }

    #[test]
    fn rows_wrap_around_a_whole_turn_only() {
        let angles = SensorProfile::builtin("vlp16")
            .expect("vlp16")
            .with_columns(32)
            .angle_grid();
        let w = angles.width;
        let config = SpatialConfig::new();
        let mut rays = vec![Ray::Unknown; angles.len()];
        rays[1] = Ray::Return(4.0);
        rays[w - 2] = Ray::Return(8.0);
        let turn = prior(&rays, &angles, true, &config);
        let crop = prior(&rays, &angles, false, &config);
        // Column 0 lies between column w - 2 (8 m, two columns away) and column 1 (4 m, one).
        let want = normalised_log(8.0 + (4.0 - 8.0) * 2.0 / 3.0);
        assert!((feature(&turn, 0)[0] - want).abs() < 1e-5);
        // In a crop it has only column 1 to its right.
        assert!((feature(&crop, 0)[0] - normalised_log(4.0)).abs() < 1e-5);
    }
}
