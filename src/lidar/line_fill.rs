//! Missing pixels of a range image filled along its lines: each from the two returns that
//! bracket it along its row (columns wrap around) or along its column, whichever pair lies
//! nearer in angle. It reaches any hole, however wide, where a local fill (within a few
//! pixels) leaves nothing, and it follows a sensor's finer axis: rows where columns are
//! dense (a VLP-16's 0.2 deg against its 2 deg beams), columns where beams are.

use super::AngleGrid;

/// Bracketing returns whose depths differ by more than this ratio lie on two surfaces: the
/// pixel takes the one nearer in angle instead of a line across the depth edge.
const EDGE_RATIO: f32 = 1.1;

/// A return that brackets a pixel along one line: its angle away and its depth.
#[derive(Clone, Copy)]
struct Side {
    angle: f32,
    depth: f32,
}

/// `observed` (row-major on `grid`, meters, 0 or not finite = no return) with each missing
/// pixel in `wanted` filled along its row or column ([`EDGE_RATIO`] at depth edges); the one
/// nearest return in angle where no line brackets the pixel; 0 where no line holds a return.
/// Observed pixels keep their depth.
pub fn fill_along_lines(
    observed: &[f32],
    grid: &AngleGrid,
    wanted: impl Fn(usize) -> bool,
) -> Vec<f32> {
    let (h, w) = (grid.height, grid.width);
    let mut out = observed.to_vec();
    if observed.len() != h * w || grid.len() != h * w || w == 0 {
        return out;
    }
    let returned = |k: usize| observed[k].is_finite() && observed[k] > 0.0;
    let column_step = std::f32::consts::TAU / w as f32;
    let elevation = |i: usize| grid.elevation_rad[i * w];
    for i in 0..h {
        // The returns of this row, for bracketing along it.
        let hits: Vec<usize> = (0..w).filter(|&j| returned(i * w + j)).collect();
        for j in 0..w {
            let k = i * w + j;
            if returned(k) {
                continue;
            }
            out[k] = 0.0;
            if !wanted(k) {
                continue;
            }
            let side_in_row = |j2: usize, steps: usize| Side {
                angle: steps as f32 * column_step,
                depth: observed[i * w + j2],
            };
            let (left, right) = match hits.len() {
                0 => (None, None),
                n => {
                    let after = hits.partition_point(|&x| x < j);
                    let next = hits[after % n];
                    let before = hits[(after + n - 1) % n];
                    (
                        Some(side_in_row(before, (j + w - before) % w)),
                        Some(side_in_row(next, (next + w - j) % w)),
                    )
                }
            };
            let side_in_column = |i2: usize| Side {
                angle: (elevation(i2) - elevation(i)).abs(),
                depth: observed[i2 * w + j],
            };
            let up = (0..i)
                .rev()
                .find(|&i2| returned(i2 * w + j))
                .map(side_in_column);
            let down = (i + 1..h)
                .find(|&i2| returned(i2 * w + j))
                .map(side_in_column);
            out[k] = fill_pixel([(left, right), (up, down)]);
        }
    }
    out
}

/// The depth of one pixel from its bracketing returns along two lines.
fn fill_pixel(lines: [(Option<Side>, Option<Side>); 2]) -> f32 {
    let bracketed = lines
        .iter()
        .filter_map(|&(a, b)| Some((a?, b?)))
        .min_by(|x, y| (x.0.angle + x.1.angle).total_cmp(&(y.0.angle + y.1.angle)));
    if let Some((a, b)) = bracketed {
        return if a.depth.max(b.depth) > EDGE_RATIO * a.depth.min(b.depth) {
            if a.angle <= b.angle { a.depth } else { b.depth }
        } else {
            let span = (a.angle + b.angle).max(f32::EPSILON);
            (a.depth * b.angle + b.depth * a.angle) / span
        };
    }
    lines
        .iter()
        .flat_map(|&(a, b)| [a, b])
        .flatten()
        .min_by(|x, y| x.angle.total_cmp(&y.angle))
        .map_or(0.0, |s| s.depth)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A `h x w` grid with beams `beam_deg` apart.
    fn grid(h: usize, w: usize, beam_deg: f32) -> AngleGrid {
        AngleGrid::regular_columns(h, w, |i| -(i as f32 * beam_deg).to_radians())
    }

    #[test]
    fn a_hole_is_filled_along_the_nearer_line_and_keeps_depth_edges() {
        // Beams 2 deg apart, columns 1 deg (360): rows bracket nearer.
        let (h, w) = (5, 360);
        let g = grid(h, w, 2.0);
        // A ramp along each row (10 m + 0.1 m per column), 20 m everywhere on row 3.
        let mut observed: Vec<f32> = (0..h * w)
            .map(|k| {
                if k / w == 3 {
                    20.0
                } else {
                    10.0 + 0.1 * (k % w) as f32
                }
            })
            .collect();
        let hole = 2 * w + 100;
        observed[hole] = 0.0;
        observed[hole + 1] = 0.0;
        let filled = fill_along_lines(&observed, &g, |_| true);
        assert!((filled[hole] - 20.0).abs() < 1e-4, "{}", filled[hole]);
        assert!((filled[hole + 1] - 20.1).abs() < 1e-4);
        // Observed pixels unchanged.
        assert_eq!(filled[0], observed[0]);
        // A whole row missing: filled along columns, the nearer side across the edge to
        // row 3 (2 deg both ways: the first side wins a tie).
        let mut no_row = observed.clone();
        no_row[2 * w..3 * w].fill(0.0);
        let filled = fill_along_lines(&no_row, &g, |_| true);
        assert!(
            (filled[2 * w + 50] - 15.0).abs() < 1e-4,
            "{}",
            filled[2 * w + 50]
        );
        // Nothing anywhere: 0; not wanted: 0.
        assert!(
            fill_along_lines(&[0.0; 10], &grid(2, 5, 1.0), |_| true)
                .iter()
                .all(|&d| d == 0.0)
        );
        let skipped = fill_along_lines(&no_row, &g, |_| false);
        assert_eq!(skipped[2 * w + 50], 0.0);
    }
}
