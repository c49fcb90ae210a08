//! Depth edges of a range image: where a return's range jumps against a neighbour's, and how
//! many pixels every return lies from the nearest such jump. The simulator's edge dropout
//! ([`crate::physics::dropout::EdgeDropout`]) and the diagnosis's edge features share it.

/// A pixel is on a depth edge when a 4-neighbour's range differs from its own by more than
/// this fraction of the nearer range.
pub const EDGE_RELATIVE_JUMP: f32 = 0.1;

/// Edge distances are counted in pixels up to this cap.
pub const MAX_EDGE_PX: u8 = 8;

/// Which neighbours make an edge and carry the distance to one.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EdgeAxes {
    /// The four neighbours.
    Both,
    /// The two in the pixel's row: the silhouettes of objects against what lies behind them.
    /// Ground seen at a grazing angle jumps between rows everywhere far off; it does not jump
    /// along a row.
    Row,
}

/// The neighbours of pixel `k` of a row-major image `width` x `height` along `axes` (columns
/// wrap around when `wrap`).
fn neighbours(
    k: usize,
    width: usize,
    height: usize,
    wrap: bool,
    axes: EdgeAxes,
) -> impl Iterator<Item = usize> {
    let (i, j) = (k / width, k % width);
    let left = match (j, wrap) {
        (0, true) => Some(i * width + width - 1),
        (0, false) => None,
        _ => Some(k - 1),
    };
    let right = match (j + 1 == width, wrap) {
        (true, true) => Some(i * width),
        (true, false) => None,
        _ => Some(k + 1),
    };
    let both = axes == EdgeAxes::Both;
    let up = (both && i > 0).then(|| k - width);
    let down = (both && i + 1 < height).then(|| k + width);
    [left, right, up, down].into_iter().flatten()
}

/// Largest depth jump at which [`edge_strength`] saturates (|ln ratio| = 1: 2.7x).
pub const EDGE_STRENGTH_CAP: f32 = 1.0;

/// Depth-edge strength of every pixel of a row-major depth image `width` wide: the largest
/// |ln(d / d_neighbour)| over its four neighbours (columns wrap around), capped at
/// [`EDGE_STRENGTH_CAP`]. Pixels without a depth (0) neither have nor make an edge.
pub fn edge_strength(depth_m: &[f32], width: usize) -> Vec<f32> {
    let height = depth_m.len() / width.max(1);
    let ln: Vec<f32> = depth_m
        .iter()
        .map(|d| if *d > 0.0 { d.ln() } else { f32::NAN })
        .collect();
    (0..depth_m.len())
        .map(|k| {
            let here = ln[k];
            if here.is_nan() {
                return 0.0;
            }
            neighbours(k, width, height, true, EdgeAxes::Both)
                .map(|m| (ln[m] - here).abs())
                .filter(|g| !g.is_nan())
                .fold(0.0f32, f32::max)
                .min(EDGE_STRENGTH_CAP)
        })
        .collect()
}

/// Pixel distance (steps through returns) from every pixel of a row-major `range_m` image
/// `width` wide to the nearest depth-edge pixel along `axes`, capped at `cap`. NaN marks no
/// return (never an edge, never a step); columns wrap around when `wrap` (a full-turn scan).
pub fn edge_proximity(
    range_m: &[f32],
    width: usize,
    wrap: bool,
    axes: EdgeAxes,
    relative_jump: f32,
    cap: u8,
) -> Vec<u8> {
    let n = range_m.len();
    let height = n / width.max(1);
    let neighbours = |k: usize| neighbours(k, width, height, wrap, axes);
    let mut dist = vec![cap; n];
    for k in 0..n {
        let r = range_m[k];
        if r.is_nan() {
            continue;
        }
        let on_edge = neighbours(k).any(|m| {
            let q = range_m[m];
            !q.is_nan() && (q - r).abs() > relative_jump * q.min(r)
        });
        if on_edge {
            dist[k] = 0;
        }
    }
    for d in 1..cap {
        let prev = dist.clone();
        for k in 0..n {
            if prev[k] <= d || range_m[k].is_nan() {
                continue;
            }
            if neighbours(k).any(|m| prev[m] == d - 1) {
                dist[k] = d;
            }
        }
    }
    dist
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_steps_from_a_depth_jump_and_wraps_on_request() {
        // 4 rows x 32 columns: a wall at 10 m on columns 0..16, at 30 m beyond.
        let range: Vec<f32> = (0..128)
            .map(|k| if k % 32 < 16 { 10.0 } else { 30.0 })
            .collect();
        let open = edge_proximity(
            &range,
            32,
            false,
            EdgeAxes::Both,
            EDGE_RELATIVE_JUMP,
            MAX_EDGE_PX,
        );
        assert_eq!((open[15], open[16], open[12], open[20]), (0, 0, 3, 4));
        assert_eq!(open[0], MAX_EDGE_PX, "capped far from the edge");
        // With wrapping, column 0 sits next to column 31: another edge.
        let wrapped = edge_proximity(
            &range,
            32,
            true,
            EdgeAxes::Both,
            EDGE_RELATIVE_JUMP,
            MAX_EDGE_PX,
        );
        assert_eq!((wrapped[0], wrapped[1]), (0, 1));
    }

    #[test]
    fn row_edges_ignore_jumps_between_rows() {
        // 3 rows x 4 columns of ground: each row 20 % farther than the one above it.
        let range: Vec<f32> = (0..12).map(|k: i32| 10.0 * 1.2f32.powi(k / 4)).collect();
        let both = edge_proximity(&range, 4, true, EdgeAxes::Both, EDGE_RELATIVE_JUMP, 4);
        assert!(
            both.iter().all(|d| *d == 0),
            "every row jumps against the next"
        );
        let row = edge_proximity(&range, 4, true, EdgeAxes::Row, EDGE_RELATIVE_JUMP, 4);
        assert!(row.iter().all(|d| *d == 4), "no row has a jump");
    }

    #[test]
    fn strength_marks_both_sides_of_a_jump_and_wrap_around() {
        // 2 rows x 4 columns: a wall at 10 m with a post at 5 m in column 1; row 1 is empty
        // but for column 3.
        let depth = [10.0, 5.0, 10.0, 10.0, 0.0, 0.0, 0.0, 40.0];
        let g = edge_strength(&depth, 4);
        let jump = 2f32.ln();
        assert!((g[0] - jump).abs() < 1e-6 && (g[1] - jump).abs() < 1e-6);
        assert!((g[2] - jump).abs() < 1e-6, "the post's other side");
        // column 3's neighbours in its row: 10 m (column 2) and, wrapping, 10 m (column 0);
        // below it 40 m: capped.
        assert_eq!(g[3], EDGE_STRENGTH_CAP);
        assert_eq!(&g[4..7], &[0.0, 0.0, 0.0], "no depth, no edge");
        assert_eq!(g[7], EDGE_STRENGTH_CAP);
    }

    #[test]
    fn missing_returns_neither_make_edges_nor_carry_distance() {
        // One row: 10 m, no return, 30 m, 30 m.
        let range = [10.0, f32::NAN, 30.0, 30.0];
        let d = edge_proximity(&range, 4, false, EdgeAxes::Both, EDGE_RELATIVE_JUMP, 4);
        assert_eq!(d, vec![4, 4, 4, 4]);
    }
}
