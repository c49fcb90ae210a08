//! Restoration of a grid from scattered returns on it (for example a random 10 % of a
//! scan's points): observed pixels keep their depth exactly, a new pixel is estimated from
//! the returns within [`SCATTER_RADIUS`] pixels ([`ScatterFill`]).
//!
//! The default estimate ([`ScatterFill::Surfaces`]) reads the returns around a new pixel as
//! local surfaces: where one plane explains them (road, walls: planes are linear in inverse
//! depth over small angles) the plane is evaluated at the new pixel; across a depth edge
//! the side that carries most of the weight (or that a guide depth agrees with) is kept.

use super::AngleGrid;

use nalgebra::{Matrix3, Vector3};

/// How [`fill_scattered`] estimates an unobserved pixel.
#[derive(Debug, Clone, Copy)]
pub enum ScatterFill<'a> {
    /// The nearest observed pixel.
    Nearest,
    /// Inverse-distance weighting of the observed pixels within twice the distance of the
    /// nearest one.
    Idw,
    /// Local surfaces ([`local_surface`]). At a depth edge, `guide` (a depth on the same
    /// grid, 0 = no opinion) picks the side whose returns' guide depths agree with the
    /// guide at the new pixel by `guide_jump` (log depth) better than the other side's.
    Surfaces {
        guide: Option<&'a [f32]>,
        guide_jump: f32,
    },
}

/// How far (in pixels) [`fill_scattered`] looks for observed pixels.
pub const SCATTER_RADIUS: isize = 8;

/// Fills `grid` (row-major, columns circular) from a scattered observation on it (meters,
/// 0 = not observed; anything not finite and positive counts as not observed): observed
/// pixels keep their depth exactly, other pixels are estimated from the observed ones within
/// [`SCATTER_RADIUS`] pixels and stay 0 where there are none.
pub fn fill_scattered(observed: &[f32], grid: &AngleGrid, how: ScatterFill) -> Vec<f32> {
    fill_scattered_where(observed, grid, how, |_| true)
}

/// [`fill_scattered_where`] with the returns' distances measured in angle (in columns:
/// a beam counts as far as its elevation step is in column steps), for grids whose beams
/// lie much farther apart than their columns (a VLP-16's 2 deg beams, 0.2 deg columns),
/// where a neighbour along the row is nearer than one along the column. The settings were
/// tuned in pixels on KITTI's HDL-64E, which [`fill_scattered_where`] keeps.
pub fn fill_scattered_in_angle(
    observed: &[f32],
    grid: &AngleGrid,
    how: ScatterFill,
    wanted: impl Fn(usize) -> bool,
) -> Vec<f32> {
    fill_scattered_with(observed, grid, how, wanted, true)
}

/// [`fill_scattered`] for the unobserved pixels `wanted` says (by index); the others stay 0
/// and cost nothing.
pub fn fill_scattered_where(
    observed: &[f32],
    grid: &AngleGrid,
    how: ScatterFill,
    wanted: impl Fn(usize) -> bool,
) -> Vec<f32> {
    fill_scattered_with(observed, grid, how, wanted, false)
}

fn fill_scattered_with(
    observed: &[f32],
    grid: &AngleGrid,
    how: ScatterFill,
    wanted: impl Fn(usize) -> bool,
    in_angle: bool,
) -> Vec<f32> {
    let (height, width) = (grid.height, grid.width);
    let mut out = vec![0.0f32; height * width];
    if observed.len() != height * width || grid.len() != height * width || width == 0 {
        return out;
    }
    let returned = |d: f32| d.is_finite() && d > 0.0;
    let column_step = std::f32::consts::TAU / width as f32;
    let mut around: Vec<Return> = Vec::new();
    let r = SCATTER_RADIUS;
    let guide_at = |idx: usize| match how {
        ScatterFill::Surfaces { guide, .. } => guide.and_then(|g| g.get(idx)).copied(),
        _ => None,
    };
    // Whether the square ring at Chebyshev distance `c` around (i, j) holds a return.
    let ring_has_return = |i: isize, j: isize, c: isize| {
        ((i - c).max(0)..(i + c + 1).min(height as isize)).any(|ii| {
            let on_edge = (ii - i).abs() == c;
            let step = if on_edge { 1 } else { 2 * c as usize };
            (-c..=c).step_by(step.max(1)).any(|dj| {
                let jj = (j + dj).rem_euclid(width as isize) as usize;
                returned(observed[ii as usize * width + jj])
            })
        })
    };
    for i in 0..height as isize {
        for j in 0..width as isize {
            let k = i as usize * width + j as usize;
            if returned(observed[k]) {
                out[k] = observed[k];
                continue;
            }
            if !wanted(k) {
                continue;
            }
            // Every fill reads only the returns within PLANE_REACH times the nearest one's
            // distance, which lie within the Chebyshev radius `reach` of the nearest ring
            // that holds one: the scan stops there (the same returns, less work).
            let Some(ring) = (1..=r).find(|&c| ring_has_return(i, j, c)) else {
                continue;
            };
            let reach =
                ((PLANE_REACH * std::f32::consts::SQRT_2 * ring as f32).ceil() as isize).min(r);
            around.clear();
            for ii in (i - reach).max(0)..(i + reach + 1).min(height as isize) {
                for dj in -reach..=reach {
                    let jj = (j + dj).rem_euclid(width as isize) as usize;
                    let idx = ii as usize * width + jj;
                    if returned(observed[idx]) {
                        let di = if in_angle {
                            (grid.elevation_rad[idx] - grid.elevation_rad[k]) / column_step
                        } else {
                            (ii - i) as f32
                        };
                        let pixels = (di * di + (dj * dj) as f32).sqrt();
                        let guide = guide_at(idx).unwrap_or(0.0);
                        around.push(Return::at(grid, k, idx, observed[idx], pixels, guide));
                    }
                }
            }
            if around.is_empty() {
                continue;
            }
            out[k] = match how {
                ScatterFill::Nearest => around
                    .iter()
                    .min_by(|a, b| a.pixels.total_cmp(&b.pixels))
                    .map_or(0.0, |r| r.depth),
                ScatterFill::Idw => idw(&within(&around, 2.0), 1),
                ScatterFill::Surfaces { guide_jump, .. } => {
                    local_surface(&around, guide_at(k).unwrap_or(0.0), guide_jump)
                }
            };
        }
    }
    out
}

/// A measured return near a new pixel: its depth, its distance in pixels, its direction
/// relative to the new pixel (degrees of elevation and azimuth) and the guide depth at it.
#[derive(Debug, Clone, Copy)]
struct Return {
    depth: f32,
    pixels: f32,
    elevation_deg: f32,
    azimuth_deg: f32,
    guide: f32,
}

impl Return {
    /// The return at pixel `idx` (`depth`, `pixels` from pixel `k`), seen from pixel `k`.
    fn at(grid: &AngleGrid, k: usize, idx: usize, depth: f32, pixels: f32, guide: f32) -> Return {
        let wrap = |a: f32| {
            let tau = std::f32::consts::TAU;
            (a + std::f32::consts::PI).rem_euclid(tau) - std::f32::consts::PI
        };
        Return {
            depth,
            pixels,
            elevation_deg: (grid.elevation_rad[idx] - grid.elevation_rad[k]).to_degrees(),
            azimuth_deg: wrap(grid.azimuth_rad[idx] - grid.azimuth_rad[k]).to_degrees(),
            guide,
        }
    }

    /// Inverse-distance weight, `power` of 1 / pixels.
    fn weight(&self, power: i32) -> f64 {
        f64::from(self.pixels.max(0.5)).powi(-power)
    }
}

// Tuned on KITTI training scans, never on the evaluation scans (BENCHMARKS.md,
// "Restoration from scattered points").
/// The plane is fitted to the returns within this many times the nearest one's distance...
const PLANE_REACH: f32 = 4.0;
/// ...when there are at least this many...
const PLANE_MIN_RETURNS: usize = 4;
/// ...and used when its weighted rms residual is below this (log depth)...
const PLANE_RMS: f64 = 0.05;
/// ...and no two of their depths, sorted, are further apart than this (log depth): two
/// surfaces, each seen along one line of returns, fit a plane exactly.
const PLANE_GAP: f32 = 0.5;
/// Otherwise the returns within this many times the nearest one's distance are blended...
const BLEND_REACH: f32 = 2.0;
/// ...from one side of their largest depth gap where it exceeds this (log depth)...
const EDGE_GAP: f32 = 0.3;
/// ...the front where the front side's local share ([`front_share`]) is at least this...
const EDGE_FRONT: f64 = 0.65;
/// ...the back where it is at most this. Far pixels lie behind an edge more often than in
/// front of it, so the back wins ties: the bounds balance the near and far fields.
const EDGE_BACK: f64 = 0.5;

/// The depth at a new pixel from the returns `around` it (at least one): an inverse-depth
/// plane where one explains the near returns; else, across a depth edge, the side the guide
/// agrees with or that the new pixel lies in, as that side's plane where one explains it;
/// else the blend, weighted towards the nearest returns.
fn local_surface(around: &[Return], guide_target: f32, guide_jump: f32) -> f32 {
    let wide = within(around, PLANE_REACH);
    if let Some(d) = plane_depth(&wide) {
        return d;
    }
    let near = within(around, BLEND_REACH);
    match edge_side(&near, &wide, guide_target, guide_jump) {
        Some(side) => side.depth(&wide),
        None => idw(&near, 3),
    }
}

/// The returns within `reach` times the distance of the nearest one.
fn within(around: &[Return], reach: f32) -> Vec<Return> {
    let nearest = around
        .iter()
        .map(|r| r.pixels)
        .fold(f32::INFINITY, f32::min);
    let limit = reach * nearest.max(0.5);
    around
        .iter()
        .filter(|r| r.pixels <= limit)
        .copied()
        .collect()
}

/// Inverse-distance weighting with weights 1 / pixels^`power`.
fn idw(returns: &[Return], power: i32) -> f32 {
    let (mut sum, mut total) = (0.0f64, 0.0f64);
    for r in returns {
        let w = r.weight(power);
        sum += w * f64::from(r.depth);
        total += w;
    }
    (sum / total) as f32
}

/// Weighted least squares of inverse depth against (1, elevation, azimuth): the depth at
/// the new pixel (the intercept) when the plane explains the returns, kept within their
/// depths.
fn plane_depth(returns: &[Return]) -> Option<f32> {
    if returns.len() < PLANE_MIN_RETURNS || largest_gap(returns).is_some_and(|(_, g)| g > PLANE_GAP)
    {
        return None;
    }
    let coef = weighted_plane(returns, |r| 1.0 / f64::from(r.depth))?;
    if coef[0] <= 0.0 {
        return None;
    }
    let (mut sq, mut total) = (0.0, 0.0);
    for r in returns {
        let fitted = coef.dot(&basis(r)).max(1e-6);
        let w = r.weight(2);
        sq += w * (fitted * f64::from(r.depth)).ln().powi(2);
        total += w;
    }
    if (sq / total).sqrt() >= PLANE_RMS {
        return None;
    }
    let (lo, hi) = returns.iter().fold((f32::INFINITY, 0.0f32), |(lo, hi), r| {
        (lo.min(r.depth), hi.max(r.depth))
    });
    Some(((1.0 / coef[0]) as f32).clamp(lo, hi))
}

/// (1, elevation, azimuth) of a return, the basis of the local planes.
fn basis(r: &Return) -> Vector3<f64> {
    Vector3::new(1.0, f64::from(r.elevation_deg), f64::from(r.azimuth_deg))
}

/// Weighted least squares (weights 1 / pixels^2) of `value` against [`basis`]: the plane's
/// coefficients, the first its value at the new pixel.
fn weighted_plane(returns: &[Return], value: impl Fn(&Return) -> f64) -> Option<Vector3<f64>> {
    // A small ridge keeps a line of returns (one row) solvable.
    let mut normal = Matrix3::identity() * 1e-4;
    let mut rhs = Vector3::zeros();
    for r in returns {
        let (x, w) = (basis(r), r.weight(2));
        normal += w * x * x.transpose();
        rhs += w * x * value(r);
    }
    normal.lu().solve(&rhs)
}

/// One side of a depth edge: its returns among the near ones, and which side it is.
struct Side {
    returns: Vec<Return>,
    front: bool,
    /// Between the two sides' depths (log-depth midpoint of the gap).
    boundary: f32,
}

impl Side {
    fn holds(&self, r: &Return) -> bool {
        (r.depth < self.boundary) == self.front
    }

    /// The side's surface at the new pixel: the plane of its returns within `wide` where one
    /// explains them, else the side's near returns blended.
    fn depth(&self, wide: &[Return]) -> f32 {
        let surface: Vec<Return> = wide.iter().filter(|r| self.holds(r)).copied().collect();
        plane_depth(&surface).unwrap_or_else(|| idw(&self.returns, 2))
    }
}

/// The new pixel's side of the largest depth gap among the `near` returns, when the gap is
/// an edge (> [`EDGE_GAP`]) and a side is clearly chosen: by the guide, or by the front
/// side's local share of the `wide` returns ([`EDGE_FRONT`], [`EDGE_BACK`]).
fn edge_side(near: &[Return], wide: &[Return], guide_target: f32, guide_jump: f32) -> Option<Side> {
    let (split, gap) = largest_gap(near)?;
    if gap <= EDGE_GAP {
        return None;
    }
    let mut sorted = near.to_vec();
    sorted.sort_by(|a, b| a.depth.total_cmp(&b.depth));
    let boundary = (sorted[split - 1].depth * sorted[split].depth).sqrt();
    let (front, back) = sorted.split_at(split);
    let front_wins = match guide_side(front, back, guide_target, guide_jump) {
        Some(side) => side,
        None => {
            let share = front_share(wide, boundary)?;
            if share >= EDGE_FRONT {
                true
            } else if share <= EDGE_BACK {
                false
            } else {
                return None;
            }
        }
    };
    let returns = if front_wins { front } else { back };
    Some(Side {
        returns: returns.to_vec(),
        front: front_wins,
        boundary,
    })
}

/// How much the new pixel belongs to the front of an edge at `boundary`: the value at the
/// pixel of a plane fitted to the `returns` read as 1 (in front) or 0 (behind). Unlike their
/// weight share, it follows the edge's line, so returns crowded on one side of the pixel do
/// not outvote the side it lies in.
fn front_share(returns: &[Return], boundary: f32) -> Option<f64> {
    weighted_plane(returns, |r| f64::from(u8::from(r.depth < boundary))).map(|c| c[0])
}

/// The largest gap between consecutive depths of `returns` (log depth), with the number of
/// returns in front of it; None for fewer than two returns.
fn largest_gap(returns: &[Return]) -> Option<(usize, f32)> {
    // Sorting the depths alone here (and the returns only in `edge_side`, which most pixels
    // never reach) measured faster than sorting the returns once for both.
    let mut depths: Vec<f32> = returns.iter().map(|r| r.depth).collect();
    depths.sort_by(f32::total_cmp);
    depths
        .windows(2)
        .enumerate()
        .map(|(i, p)| (i + 1, (p[1] / p[0]).ln()))
        .max_by(|a, b| a.1.total_cmp(&b.1))
}

/// Whether the guide puts the new pixel on the front side (true) or the back side (false):
/// the side whose weighted guide depth lies nearer the guide at the new pixel, by more than
/// `guide_jump` (log depth). None without a guide at every return and the new pixel.
fn guide_side(front: &[Return], back: &[Return], target: f32, guide_jump: f32) -> Option<bool> {
    let all_guided = front.iter().chain(back).all(|r| r.guide > 0.0);
    if target <= 0.0 || !all_guided {
        return None;
    }
    let miss = |s: &[Return]| {
        let total: f64 = s.iter().map(|r| r.weight(2)).sum();
        let g = s
            .iter()
            .map(|r| r.weight(2) * f64::from(r.guide))
            .sum::<f64>()
            / total;
        (g / f64::from(target)).ln().abs()
    };
    let (f, b) = (miss(front), miss(back));
    let margin = f64::from(guide_jump);
    if f + margin < b {
        Some(true)
    } else if b + margin < f {
        Some(false)
    } else {
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// 16 x 512 grid (0.4 deg rows, 0.7 deg columns): a wall at 10 m on the left half,
    /// 40 m on the right; 10 % observed.
    fn scattered_edge() -> (AngleGrid, Vec<f32>, Vec<f32>) {
        let (h, w) = (16, 512);
        let grid = AngleGrid::regular_columns(h, w, |i| (0.4 * (8.0 - i as f32)).to_radians());
        let truth: Vec<f32> = (0..h * w)
            .map(|k| if k % w < w / 2 { 10.0 } else { 40.0 })
            .collect();
        let observed = (0..h * w)
            .map(|k| if (k * 7919) % 10 == 0 { truth[k] } else { 0.0 })
            .collect();
        (grid, truth, observed)
    }

    /// Mean absolute error of `out` against `truth` on the pixels not observed.
    fn mae(out: &[f32], truth: &[f32], observed: &[f32]) -> f32 {
        let held: Vec<usize> = (0..truth.len()).filter(|k| observed[*k] == 0.0).collect();
        held.iter()
            .map(|k| (out[*k] - truth[*k]).abs())
            .sum::<f32>()
            / held.len() as f32
    }

    /// Plain IDW and unguided local surfaces of `observed`, with their MAEs against `truth`.
    fn idw_and_surfaces(
        observed: &[f32],
        truth: &[f32],
        grid: &AngleGrid,
        guide_jump: f32,
    ) -> ((Vec<f32>, f32), (Vec<f32>, f32)) {
        let plain = fill_scattered(observed, grid, ScatterFill::Idw);
        let local = ScatterFill::Surfaces {
            guide: None,
            guide_jump,
        };
        let out = fill_scattered(observed, grid, local);
        let (e_plain, e_out) = (mae(&plain, truth, observed), mae(&out, truth, observed));
        ((plain, e_plain), (out, e_out))
    }

    #[test]
    fn scattered_fill_keeps_returns_and_never_averages_across_the_edge() {
        let (grid, truth, observed) = scattered_edge();
        let ((plain, e_plain), (out, e_out)) = idw_and_surfaces(&observed, &truth, &grid, 0.0);
        assert!(
            plain.iter().any(|d| *d > 11.0 && *d < 39.0),
            "plain IDW smears the edge"
        );
        assert!(
            e_out < 0.75 * e_plain,
            "surfaces {e_out} m, IDW {e_plain} m"
        );
        // Away from the edges (columns 0 and 256) every pixel lies on its own wall.
        let away = |k: &usize| (4..252).contains(&(k % grid.width % 256));
        for k in (0..truth.len()).filter(away) {
            assert!((out[k] - truth[k]).abs() < 1e-3, "pixel {k}: {}", out[k]);
        }
        // A guide that sees the edge exactly puts every pixel on its side: any margin would
        // leave a tie to the weights, so none.
        let guided = ScatterFill::Surfaces {
            guide: Some(&truth),
            guide_jump: 0.0,
        };
        let out = fill_scattered(&observed, &grid, guided);
        for k in 0..truth.len() {
            if observed[k] > 0.0 {
                assert_eq!(out[k].to_bits(), observed[k].to_bits(), "return {k} kept");
            }
            assert!((out[k] - truth[k]).abs() < 1e-3, "pixel {k}: {}", out[k]);
        }
    }

    #[test]
    fn values_that_are_not_returns_are_not_observed() {
        let (grid, _, mut observed) = scattered_edge();
        let clean = fill_scattered(&observed, &grid, ScatterFill::Idw);
        // Pixels 11, 21 and 31 were not observed (every 10th pixel is).
        let (nan, inf, negative) = (11, 21, 31);
        observed[nan] = f32::NAN;
        observed[inf] = f32::INFINITY;
        observed[negative] = -5.0;
        for how in [ScatterFill::Idw, ScatterFill::Nearest] {
            let out = fill_scattered(&observed, &grid, how);
            assert!(out.iter().all(|d| d.is_finite() && *d >= 0.0));
        }
        let out = fill_scattered(
            &observed,
            &grid,
            ScatterFill::Surfaces {
                guide: None,
                guide_jump: 0.3,
            },
        );
        assert!(out.iter().all(|d| d.is_finite() && *d >= 0.0));
        // The bad values sit where nothing was observed, so plain IDW is unchanged.
        assert_eq!(fill_scattered(&observed, &grid, ScatterFill::Idw), clean);
    }

    #[test]
    fn the_road_between_scattered_returns_is_a_plane_in_inverse_depth() {
        // Level road 1.7 m below a 64-beam sensor (rows 0.4 deg apart, 2 to 27 deg down):
        // depth 1.7 / sin(-elevation), 10 % of the pixels observed at random.
        let (h, w) = (64, 512);
        let grid = AngleGrid::regular_columns(h, w, |i| (-2.0 - 0.4 * i as f32).to_radians());
        let truth: Vec<f32> = grid
            .elevation_rad
            .iter()
            .map(|e| 1.7 / (-e).sin())
            .collect();
        // A multiplicative hash of the pixel index scatters the observed ones.
        let observed: Vec<f32> = (0..h * w)
            .map(|k| {
                let hash = (k as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 54;
                if hash.is_multiple_of(10) {
                    truth[k]
                } else {
                    0.0
                }
            })
            .collect();
        let ((_, e_plain), (_, e_plane)) = idw_and_surfaces(&observed, &truth, &grid, 0.3);
        assert!(
            e_plane < 0.25 * e_plain,
            "plane {e_plane} m, IDW {e_plain} m"
        );
    }

    #[test]
    fn a_pixel_on_an_edge_takes_the_side_it_lies_in_not_the_nearer_returns() {
        // A vertical edge: a pole at 10 m left of the new pixel's column, a wall at 40 m from
        // it on. The pole's returns are the nearest; the wall's lie in the pixel's own column
        // (two rows up and down) and to its right.
        let at = |row: f32, col: f32, depth: f32| Return {
            depth,
            pixels: (row * row + col * col).sqrt(),
            elevation_deg: 0.4 * row,
            azimuth_deg: 0.7 * col,
            guide: 0.0,
        };
        let around = [
            at(0.0, -1.0, 10.0),
            at(-1.0, -1.0, 10.0),
            at(1.0, -1.0, 10.0),
            at(-2.0, 0.0, 40.0),
            at(2.0, 0.0, 40.0),
            at(0.0, 2.0, 40.0),
            at(-2.0, 1.0, 40.0),
            at(2.0, 1.0, 40.0),
        ];
        let near = within(&around, BLEND_REACH);
        let weight = |front: bool| {
            near.iter()
                .filter(|r| (r.depth < 20.0) == front)
                .map(|r| r.weight(2))
                .sum::<f64>()
        };
        assert!(
            weight(true) > 2.0 * weight(false),
            "the pole carries most of the weight"
        );
        let share = front_share(&within(&around, PLANE_REACH), 20.0).unwrap();
        assert!(share < EDGE_BACK, "front share {share}");
        assert_eq!(local_surface(&around, 0.0, 0.3), 40.0);
    }

    #[test]
    fn in_angle_a_beam_far_apart_counts_as_far() {
        // Beams 2 deg apart, columns 0.2 deg (1800): a wall at 10 m on row 1, its neighbours
        // rows at 30 m; one pixel of the wall missing. In pixels the rows a beam away are as
        // near as the row's own neighbours; in angle they are ten times farther.
        let (h, w) = (3, 1800);
        let grid = AngleGrid::regular_columns(h, w, |i| -(2.0 * i as f32).to_radians());
        let mut observed: Vec<f32> = (0..h * w)
            .map(|k| if k / w == 1 { 10.0 } else { 30.0 })
            .collect();
        let hole = w + 900;
        observed[hole] = 0.0;
        let how = ScatterFill::Idw;
        let in_pixels = fill_scattered_where(&observed, &grid, how, |_| true)[hole];
        let in_angle = fill_scattered_in_angle(&observed, &grid, how, |_| true)[hole];
        assert!((in_angle - 10.0).abs() < 1e-3, "{in_angle}");
        assert!(in_pixels > 12.0, "{in_pixels}");
    }
}
