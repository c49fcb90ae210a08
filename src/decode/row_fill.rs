//! A learned correction of the edge-aware fill for rows restored between kept beams
//! (`--restore-lines`, upsampling in beams): a small network reads the kept returns around
//! a restored pixel (two kept beams above, two below, five columns) relative to the
//! edge-aware value there, and moves that value along its ray. Interpolation cannot tell
//! whether a pixel between two beams at different depths lies on the near surface or the
//! far one; the pattern of returns around it often can. Trained on KITTI training drives
//! ([`crate::train::row_fill`]; `cargo run --release --example row_fill_fit` rebuilds the
//! shipped `models/row_fill.json`, which is built into the binary).

use std::path::Path;
use std::sync::OnceLock;

use anyhow::{Context, Result, bail};
use serde::{Deserialize, Serialize};

use crate::lidar::{AngleGrid, RangeImage, SurfaceRule, resample_by_surface};
use crate::util::mlp::Mlp;

/// Which kept returns around a restored pixel the network reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Window {
    /// Kept beams on each side (above and below).
    pub beams_per_side: usize,
    /// Columns on each side of the pixel's own.
    pub half_columns: usize,
}

impl Window {
    fn returns(&self) -> usize {
        2 * self.beams_per_side * (2 * self.half_columns + 1)
    }

    /// Inputs per pixel: each window return's log depth relative to the starting depth and
    /// whether it is there, then where the pixel sits between its beams, the beams' spacing,
    /// its log depth, its row, the fill's log depth at the two neighbouring columns, and
    /// whether the start is the fill's (0) or the nearest kept return's (1).
    pub fn features(&self) -> usize {
        2 * self.returns() + 7
    }
}

impl Default for Window {
    fn default() -> Self {
        Window {
            beams_per_side: 2,
            half_columns: 2,
        }
    }
}

/// Largest move along the ray, in log depth (a factor of e): the correction refines the
/// fill, it does not replace it.
pub const MAX_MOVE: f32 = 2.0;
/// Log-depth ratios are clamped to this before they enter the network.
const MAX_RATIO: f32 = 3.0;

/// The trained correction, as saved in `row_fill.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RowFill {
    pub window: Window,
    pub net: Mlp,
}

impl RowFill {
    /// The network shipped in `models/row_fill.json`, built into the binary.
    pub fn shipped() -> &'static RowFill {
        static SHIPPED: OnceLock<RowFill> = OnceLock::new();
        SHIPPED.get_or_init(|| {
            Self::parse(include_str!("../../models/row_fill.json"))
                .expect("the shipped row fill is checked by a unit test")
        })
    }

    pub fn new(window: Window, net: Mlp) -> RowFill {
        RowFill { window, net }
    }

    pub fn load(path: &Path) -> Result<RowFill> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("cannot read the row fill '{}'", path.display()))?;
        Self::parse(&text).with_context(|| format!("'{}' is not a row fill", path.display()))
    }

    fn parse(text: &str) -> Result<RowFill> {
        let fill: RowFill = serde_json::from_str(text)?;
        let Window {
            beams_per_side,
            half_columns,
        } = fill.window;
        if !(1..=8).contains(&beams_per_side) || half_columns > 16 {
            bail!(
                "its window ({beams_per_side} beams a side, {half_columns} columns a side) is out of range"
            );
        }
        let features = fill.window.features();
        if !fill.net.takes(features, 1) {
            bail!(
                "its network takes {} inputs where its window gives {features}",
                fill.net.inputs()
            );
        }
        Ok(fill)
    }

    /// `reference` (the edge-aware fill of the rows between `kept`) with every restored
    /// pixel between two kept beams moved by the network; where the fill left a hole (its
    /// nearest kept pixel dropped the ray) the network starts from the nearest kept return
    /// in the window instead. Kept rows, the rows outside the outermost kept beams and
    /// pixels with no kept return in their window stay as they are.
    pub fn refine(
        &self,
        observed: &[f32],
        reference: &[f32],
        grid: &AngleGrid,
        kept: &[usize],
    ) -> Vec<f32> {
        let restored = restored_features(self.window, observed, reference, grid, kept);
        let moves = self.net.forward(&restored.x);
        let mut out = reference.to_vec();
        for ((k, start), m) in restored.pixels.into_iter().zip(restored.start).zip(moves) {
            out[k] = moved(start, m);
        }
        out
    }
}

/// `depth` moved along its ray by the network's output `m` (log depth, clamped).
pub fn moved(depth: f32, m: f32) -> f32 {
    depth * m.clamp(-MAX_MOVE, MAX_MOVE).exp()
}

/// The edge-aware fill of every row of `grid` from the `kept` rows of `observed` (model-grid
/// depths, 0 = no return), as `convert` restores them; 0 where no kept return reaches.
pub fn edge_aware_rows(grid: &AngleGrid, observed: &[f32], kept: &[usize]) -> Vec<f32> {
    let source = rows_image(grid, observed, kept);
    resample_by_surface(&source, grid, &SurfaceRule::default(), None).range_m
}

/// Rows `rows` of a model-grid depth as their own range image (with their angles).
pub(super) fn rows_image(grid: &AngleGrid, depth: &[f32], rows: &[usize]) -> RangeImage {
    let w = grid.width;
    let pick = |field: &[f32]| -> Vec<f32> {
        rows.iter()
            .flat_map(|r| field[r * w..(r + 1) * w].iter().copied())
            .collect()
    };
    let angles = AngleGrid {
        height: rows.len(),
        width: w,
        elevation_rad: pick(&grid.elevation_rad),
        azimuth_rad: pick(&grid.azimuth_rad),
    };
    let mut image = RangeImage::empty(angles);
    image.range_m = pick(depth);
    image
}

/// The restored pixels the network moves, where it starts each (the fill, or where the fill
/// left a hole the nearest kept return in the window), and their features,
/// [`Window::features`] per pixel.
pub(crate) struct Restored {
    pub pixels: Vec<usize>,
    pub start: Vec<f32>,
    pub x: Vec<f32>,
}

pub(crate) fn restored_features(
    window: Window,
    observed: &[f32],
    reference: &[f32],
    grid: &AngleGrid,
    kept: &[usize],
) -> Restored {
    let (h, w) = (grid.height, grid.width);
    let mut out = Restored {
        pixels: Vec::new(),
        start: Vec::new(),
        x: Vec::new(),
    };
    for r in 0..h {
        let Some(beams) = Beams::around(kept, r, window.beams_per_side) else {
            continue;
        };
        for c in 0..w {
            let k = r * w + c;
            let (start, hole) = match reference[k] {
                d if d > 0.0 => (d, false),
                _ => match beams.nearest_return(observed, w, c, window.half_columns) {
                    Some(d) => (d, true),
                    None => continue,
                },
            };
            out.pixels.push(k);
            out.start.push(start);
            let at = Start {
                r,
                c,
                depth: start,
                hole,
            };
            push_features(window, observed, reference, (h, w), &beams, &at, &mut out.x);
        }
    }
    out
}

/// Where the network starts at a restored pixel.
struct Start {
    r: usize,
    c: usize,
    depth: f32,
    /// The fill left a hole here; the start is the nearest kept return.
    hole: bool,
}

/// The kept rows around a restored row, `per_side` above and below (top to bottom; `None`
/// past the first or last), and where the row sits between the nearest two.
struct Beams {
    rows: Vec<Option<usize>>,
    between: f32,
    spacing: f32,
}

impl Beams {
    fn around(kept: &[usize], r: usize, per_side: usize) -> Option<Beams> {
        let below = kept.iter().position(|&q| q > r)?;
        if below == 0 || kept[below - 1] == r {
            return None;
        }
        let (a, b) = (kept[below - 1], kept[below]);
        let rows = (below as isize - per_side as isize..(below + per_side) as isize)
            .map(|i| usize::try_from(i).ok().and_then(|i| kept.get(i).copied()))
            .collect();
        Some(Beams {
            rows,
            between: (r - a) as f32 / (b - a) as f32,
            spacing: (b - a) as f32 / 8.0,
        })
    }

    /// The first kept return at column `c`, then `c - 1`, `c + 1`, ... up to `half_columns`
    /// away, taking the beams nearest first at each column (of two equally near, the one on
    /// the side the row is nearer to).
    fn nearest_return(
        &self,
        observed: &[f32],
        w: usize,
        c: usize,
        half_columns: usize,
    ) -> Option<f32> {
        let n = self.rows.len() / 2;
        let below_first = self.between > 0.5;
        let pair = |j: usize| {
            let (above, below) = (self.rows[n - 1 - j], self.rows[n + j]);
            if below_first {
                [below, above]
            } else {
                [above, below]
            }
        };
        let offsets = (0..=2 * half_columns as isize).map(|t| match t {
            0 => 0,
            t if t % 2 == 1 => -(t + 1) / 2,
            t => t / 2,
        });
        offsets
            .map(|dc| (c as isize + dc).rem_euclid(w as isize) as usize)
            .flat_map(|col| {
                (0..n)
                    .flat_map(pair)
                    .flatten()
                    .map(move |q| observed[q * w + col])
            })
            .find(|&d| d > 0.0)
    }
}

fn push_features(
    window: Window,
    observed: &[f32],
    reference: &[f32],
    (h, w): (usize, usize),
    beams: &Beams,
    at: &Start,
    x: &mut Vec<f32>,
) {
    let (r, c, here) = (at.r, at.c, at.depth);
    let ratio = |d: f32| (d / here).ln().clamp(-MAX_RATIO, MAX_RATIO);
    let column = |dc: isize| (c as isize + dc).rem_euclid(w as isize) as usize;
    let half = window.half_columns as isize;
    for &row in &beams.rows {
        for dc in -half..=half {
            let d = row.map_or(0.0, |q| observed[q * w + column(dc)]);
            let (v, m) = if d > 0.0 { (ratio(d), 1.0) } else { (0.0, 0.0) };
            x.push(v);
            x.push(m);
        }
    }
    let side = |dc: isize| {
        let d = reference[r * w + column(dc)];
        if d > 0.0 { ratio(d) } else { 0.0 }
    };
    x.extend([
        beams.between,
        beams.spacing,
        here.ln() / 4.0,
        r as f32 / h as f32,
        side(-1),
        side(1),
        f32::from(u8::from(at.hole)),
    ]);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::util::rng::Rng;

    fn grid(h: usize, w: usize) -> AngleGrid {
        let mut elevation_rad = Vec::new();
        let mut azimuth_rad = Vec::new();
        for r in 0..h {
            for c in 0..w {
                elevation_rad.push(0.1 - 0.01 * r as f32);
                azimuth_rad
                    .push(std::f32::consts::PI - c as f32 * 2.0 * std::f32::consts::PI / w as f32);
            }
        }
        AngleGrid {
            height: h,
            width: w,
            elevation_rad,
            azimuth_rad,
        }
    }

    #[test]
    fn the_shipped_network_loads_and_moves_a_restored_row() {
        let fill = RowFill::shipped();
        let g = grid(16, 32);
        let observed: Vec<f32> = (0..16 * 32).map(|k| 5.0 + (k % 7) as f32).collect();
        let kept = [0, 4, 8, 12];
        let reference = edge_aware_rows(&g, &observed, &kept);
        let out = fill.refine(&observed, &reference, &g, &kept);
        for r in kept {
            assert_eq!(out[r * 32..(r + 1) * 32], reference[r * 32..(r + 1) * 32]);
        }
        assert_ne!(out, reference);
    }

    #[test]
    fn beams_around_a_row_are_the_nearest_kept_ones() {
        let kept = [0, 4, 8, 12];
        let b = Beams::around(&kept, 5, 2).unwrap();
        assert_eq!(b.rows, [Some(0), Some(4), Some(8), Some(12)]);
        assert_eq!(b.between, 0.25);
        let b = Beams::around(&kept, 2, 2).unwrap();
        assert_eq!(b.rows, [None, Some(0), Some(4), Some(8)]);
        let b = Beams::around(&kept, 9, 1).unwrap();
        assert_eq!(b.rows, [Some(8), Some(12)]);
        assert!(
            Beams::around(&kept, 4, 2).is_none(),
            "a kept row is not restored"
        );
        assert!(
            Beams::around(&kept, 13, 2).is_none(),
            "nothing below the last beam"
        );
    }

    #[test]
    fn an_untrained_correction_leaves_the_fill_as_it_is() {
        let g = grid(16, 32);
        let observed: Vec<f32> = (0..16 * 32).map(|k| 5.0 + (k % 7) as f32).collect();
        let kept = [0, 4, 8, 12];
        let reference = edge_aware_rows(&g, &observed, &kept);
        let window = Window::default();
        let net = Mlp::new(&[window.features(), 8, 1], &mut Rng::new(1));
        let fill = RowFill::new(window, net);
        assert_eq!(fill.refine(&observed, &reference, &g, &kept), reference);
        let restored = restored_features(window, &observed, &reference, &g, &kept);
        assert_eq!(restored.x.len(), restored.pixels.len() * window.features());
        assert!(
            restored
                .pixels
                .iter()
                .all(|k| !kept.contains(&(k / 32)) && k / 32 < 12)
        );
    }

    #[test]
    fn a_hole_starts_from_the_nearest_kept_return() {
        let kept = [0, 4, 8, 12];
        let w = 8;
        let mut observed = vec![0.0f32; 16 * w];
        observed[4 * w + 3] = 10.0; // above, one column off
        observed[8 * w + 3] = 20.0; // below, in the same column
        observed[12 * w + 4] = 30.0; // the outer beam below, in the column itself
        let b = Beams::around(&kept, 5, 2).unwrap();
        assert_eq!(b.nearest_return(&observed, w, 4, 2), Some(30.0));
        observed[12 * w + 4] = 0.0;
        // Row 5 is nearer the beam above, row 7 the one below.
        assert_eq!(b.nearest_return(&observed, w, 4, 2), Some(10.0));
        let b = Beams::around(&kept, 7, 2).unwrap();
        assert_eq!(b.nearest_return(&observed, w, 4, 2), Some(20.0));
        assert_eq!(b.nearest_return(&observed, w, 4, 0), None);
    }
}
