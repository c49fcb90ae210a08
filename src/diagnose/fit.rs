//! Maximum-likelihood selection of the drop models a simulator left out.
//!
//! Every pixel of a real scan is kept with probability
//! `keep = c · B(x) · Π_e (1 − p_e(x))`:
//! - `B(x)`, the **baseline**, is the simulated recording's own keep rate in the
//!   pixel's (row, completed-range) cell, smoothed towards the range marginal. It
//!   holds what both sides share (no-hit sky, the sensor's reach, fill artefacts)
//!   and the simulator's physics as given.
//! - `c` is a free keep-rate scale (the null model: "only the overall rate differs").
//! - `p_e` are candidate effects ([`DropFamily`]): each maps a pixel to one bin of
//!   its own feature (range, cos incidence, row, class, row × azimuth cell) and
//!   fits a drop probability per bin (a parametric curve or free rates).
//!
//! Selection is greedy forward: each round fits every remaining candidate on the
//! real *training* scans given the effects already chosen, and keeps the one
//! whose held-out gain (NLL per pixel on the real *test* scans, over the current
//! model with `c` refitted) beats its penalty (BIC term, at least
//! [`MIN_GAIN_NATS`]); of two that read the same drops, the one with fewer
//! parameters ([`simpler_rival`]). Nothing is claimed that does not beat the null on
//! held-out data.
//!
//! Fitting one candidate given the others is cheap: pixels are pooled into a
//! [`QTable`] by (candidate bin, level of the rest-of-model keep probability `q`),
//! and the likelihood of any per-bin drop curve is a sum over its cells.

use super::features::ScanFeatures;
use crate::model::calibration::bernoulli_nll;

/// Smallest held-out gain (nats per pixel) an effect must show: pixels of a scan
/// are correlated, so the BIC term alone (which assumes independence) is too lax.
pub const MIN_GAIN_NATS: f64 = 3e-3;

/// Pixels completed to near the sensor's reach are ambiguous: "no surface within
/// reach" (scene) or "dropped" (physics); their share depends on the scene, so
/// the fit leaves out completed ranges above `REACH_FRACTION` times the sim's
/// `REACH_QUANTILE` quantile of kept ranges.
pub const REACH_QUANTILE: f64 = 0.995;
pub const REACH_FRACTION: f32 = 0.85;

/// Width of the baseline's range cells, meters.
const BASELINE_RANGE_BIN_M: f32 = 2.0;
/// Prior weight (pixels) of the coarser rate in each baseline cell.
const SMOOTHING_PIXELS: f64 = 20.0;
/// Levels of `1 - q` (log scale) in a [`QTable`].
const Q_LEVELS: usize = 96;
const Q_FLOOR: f64 = 1e-5;
/// Largest keep probability a model may give (keeps logs finite).
const KEEP_MAX: f64 = 1.0 - 1e-7;

/// The range beyond which completed pixels are left out: [`REACH_FRACTION`] of
/// the sim's [`REACH_QUANTILE`] kept-range quantile. The sim's alone: a real
/// sensor that loses far returns shows range physics to be found, not a reach
/// to cut away.
pub fn reach_m(sim: &[ScanFeatures]) -> f32 {
    REACH_FRACTION * kept_range_quantile(sim, REACH_QUANTILE)
}

/// The `q` quantile of kept ranges over scans (infinity when none is kept).
pub fn kept_range_quantile(scans: &[ScanFeatures], q: f64) -> f32 {
    let mut ranges: Vec<f32> = scans
        .iter()
        .flat_map(|f| (0..f.len()).filter(|&k| f.kept[k]).map(|k| f.range_m[k]))
        .filter(|r| r.is_finite())
        .collect();
    if ranges.is_empty() {
        return f32::INFINITY;
    }
    let i = ((ranges.len() - 1) as f64 * q.clamp(0.0, 1.0)) as usize;
    *ranges.select_nth_unstable_by(i, f32::total_cmp).1
}

/// Largest enclosure distance [`Pixels::enclosure_px`] tells apart.
pub const ENCLOSURE_CAP_PX: u8 = 16;

/// Two returns enclose a pixel as one surface ([`Pixels::surface_px`]) when their
/// inverse ranges differ by at most this share of the larger one, or, above and below
/// it, their heights do (one level plane: the ground, a ceiling).
const SURFACE_TOLERANCE: f32 = 0.15;
/// Heights nearer the sensor's than this (m) do not tell a level plane: at the horizon
/// every surface has them.
const LEVEL_MIN_HEIGHT_M: f32 = 0.5;

/// [`Pixels::enclosure_px`] and [`Pixels::surface_px`] of every pixel of one scan, from
/// one search for each pixel's nearest returns.
fn enclosures(f: &ScanFeatures) -> (Vec<u8>, Vec<u8>) {
    let (h, w) = (f.height, f.width.max(1));
    let cap = usize::from(ENCLOSURE_CAP_PX);
    // Distance to the nearest return from `k` in steps of `step`, at most `limit` steps.
    let reach = |k: usize, step: isize, limit: usize| -> usize {
        (1..=cap.min(limit))
            .find(|&d| f.kept[(k as isize + step * d as isize) as usize])
            .unwrap_or(cap)
    };
    // The farther of the nearest returns on both sides, `step` apart, within `before`
    // and `after` steps: as any returns, and as one surface (their inverse ranges
    // within `SURFACE_TOLERANCE` of each other).
    let side = |k: usize, step: isize, before: usize, after: usize| -> (usize, usize) {
        let a = reach(k, -step, before);
        let b = reach(k, step, after);
        if a >= cap || b >= cap {
            return (cap, cap);
        }
        let (ka, kb) = (
            (k as isize - step * a as isize) as usize,
            (k as isize + step * b as isize) as usize,
        );
        let (ua, ub) = (1.0 / f.range_m[ka], 1.0 / f.range_m[kb]);
        let near = |x: f32, y: f32| (x - y).abs() <= SURFACE_TOLERANCE * x.abs().max(y.abs());
        // Along a column, the heights of the two returns, where both lie at least
        // `LEVEL_MIN_HEIGHT_M` above or below the sensor (nearer, at the horizon,
        // every surface has such heights).
        let heights = (step != 1)
            .then(|| {
                let height = |k: usize| f.range_m[k] * f.elevation_rad[k].sin();
                (height(ka), height(kb))
            })
            .filter(|(za, zb)| za.abs().min(zb.abs()) >= LEVEL_MIN_HEIGHT_M);
        let mut level = false;
        if let Some((za, zb)) = heights {
            // A return above the sensor and one below it (a ceiling and the floor of a
            // corridor, a crown and the road) leave the horizon between them open: the
            // rays there may pass both.
            if za * zb < 0.0 {
                return (cap, cap);
            }
            // Rows of a sparse sensor meet the ground at ranges far apart, at one height.
            level = near(za, zb);
        }
        let one_surface = near(ua, ub) || level;
        (a.max(b), if one_surface { a.max(b) } else { cap })
    };
    (0..f.len())
        .map(|k| {
            let (i, j) = (k / w, k % w);
            let row = side(k, 1, j, w - 1 - j);
            let column = side(k, w as isize, i, h - 1 - i);
            (row.0.min(column.0) as u8, row.1.min(column.1) as u8)
        })
        .unzip()
}

/// [`Pixels::laser_px`] of every pixel of one scan: `surface` ([`enclosures`]), and the
/// bottom row under level ground. The bottom row has nothing below it; where the two
/// nearest returns above a pixel there lie on one level plane below the sensor, the
/// ground runs on towards the car under it: the pixel sees that ground or lost its ray
/// (a dead bottom laser). Kept and dropped pixels alike, from the returns above only.
fn laser_enclosures(f: &ScanFeatures, surface: &[u8]) -> Vec<u8> {
    let (h, w) = (f.height, f.width.max(1));
    let cap = usize::from(ENCLOSURE_CAP_PX);
    let mut out = surface.to_vec();
    if h < 3 {
        return out;
    }
    // The nearest return above `k` (its index and distance in rows), within the cap.
    let above = |k: usize| -> Option<(usize, usize)> {
        (1..=cap.min(k / w))
            .find(|&d| f.kept[k - d * w])
            .map(|d| (k - d * w, d))
    };
    let height = |k: usize| f.range_m[k] * f.elevation_rad[k].sin();
    let bottom = (h - 1) * w;
    for (k, slot) in out.iter_mut().enumerate().skip(bottom) {
        let Some((ka, a)) = above(k) else { continue };
        let Some((kb, _)) = above(ka) else { continue };
        let (za, zb) = (height(ka), height(kb));
        let level = za <= -LEVEL_MIN_HEIGHT_M
            && zb <= -LEVEL_MIN_HEIGHT_M
            && (za - zb).abs() <= SURFACE_TOLERANCE * za.abs().max(zb.abs());
        if level {
            *slot = (*slot).min(a as u8);
        }
    }
    out
}

/// Elevation above which a pixel without geometry may be open space rather than
/// a dropped ray: where a level ground `h` below the sensor lies beyond
/// `GROUND_REACH_FRACTION` of the reach, `h` the median height of the bottom
/// row's returns below the sensor. Whether a scene has sky or open space there
/// is not physics, whatever the sensor's field of view; below it the ground is
/// within reach, so a pixel without a return there lost its ray. Without a
/// usable ground estimate: the horizon (elevation 0).
/// `ground_m` is [`ground_depth_m`] of the scans, None where it or the reach is unknown.
fn open_elevation_rad(ground_m: Option<f32>, reach_m: f32) -> f32 {
    const GROUND_REACH_FRACTION: f32 = 0.8;
    ground_m.map_or(0.0, |h| {
        -(h / (GROUND_REACH_FRACTION * reach_m))
            .clamp(0.0, 1.0)
            .asin()
    })
}

/// A dropped pixel is enclosed when returns lie on both sides of it within this many
/// pixels along its row or its column ([`Pixels::enclosure_px`]).
pub const ENCLOSED_PX: u8 = 8;

/// For each pixel of a scan on the open ground within reach, the level ground's range
/// `h / sin(-e)` (else NaN): dropped, not enclosed by returns (the fill copied some
/// outline's range into it), below `open_above` (the ground lies within reach there),
/// its ground point beyond every return of its column (nearer, the ground was in
/// sight: an object lost its rays, and the feature fill completes it), and no return
/// above it standing nearer than that ground point (a wall it would hit first).
/// A column whose returns all lie in the near field qualifies too: where grazing
/// incidence empties the ground from a few metres on (a low-resolution sensor's
/// ground rows), that is all a column keeps.
fn open_ground_range(f: &ScanFeatures, enclosure: &[u8], open_above: f32, h: f32) -> Vec<f32> {
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
fn ground_depth_m(scans: &[ScanFeatures]) -> Option<f32> {
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
fn ceiling_height_m(scans: &[ScanFeatures]) -> Option<f32> {
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
fn ceiling_range(f: &ScanFeatures, h: f32, reach_m: f32) -> Vec<f32> {
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

/// The pixels a fit uses, pooled over scans (struct of arrays). Left out: pixels
/// completed beyond the reach, and pixels without geometry where open space is
/// possible ([`open_elevation_rad`]: whether a scene has sky there is not
/// physics).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Pixels {
    pub height: usize,
    pub width: usize,
    /// The sim's reach the pixels were collected within (m).
    pub reach_m: f32,
    pub row: Vec<u16>,
    pub column: Vec<u16>,
    /// Completed range (NaN = no geometry).
    pub range_m: Vec<f32>,
    /// cos(incidence) of the completed surface (NaN = unknown).
    pub cos_incidence: Vec<f32>,
    pub class: Vec<u16>,
    pub kept: Vec<bool>,
    /// The smallest `d` such that the pixel has returns on both sides within `d`
    /// pixels along its row or along its column (capped at [`ENCLOSURE_CAP_PX`]),
    /// the pixel itself not counted. A small value means it lies within a
    /// surface (a dropped one's completion interpolates it rather than
    /// extrapolating from an object's outline into open space). Read from the
    /// neighbours only, so that selecting pixels by it selects kept and dropped
    /// ones alike: counting every kept pixel as enclosed would make the set of
    /// enclosed pixels depend on the outcome being modelled.
    pub enclosure_px: Vec<u8>,
    /// As `enclosure_px`, with the two returns on one surface (their ranges within
    /// [`SURFACE_TOLERANCE`]): a hole in a wall, not a gap between two tree crowns
    /// at different ranges that shows the sky. Which share of the pixels beside
    /// an object's outline open onto the sky is the scene's; the baseline's split
    /// uses this, `beam_dropout` its [`Pixels::laser_px`].
    pub surface_px: Vec<u8>,
    /// As `surface_px`, with the bottom row under level ground enclosed by it
    /// ([`laser_enclosures`]): what a laser can hit, for `beam_dropout`.
    pub laser_px: Vec<u8>,
    /// A dropped pixel on the open ground within reach ([`open_ground_range`]) or
    /// under a level ceiling ([`ceiling_range`]), completed as that plane (range and
    /// incidence): where strong range or incidence physics empties the far field or a
    /// garage's ceiling, no return is left to complete it from, and the fill's copied
    /// range (a wall's) would hide the loss.
    pub level_plane: Vec<bool>,
    /// Pixels (4-connected steps) to the nearest depth edge of the completed range, capped.
    pub edge_px: Vec<u8>,
    /// The same along the row only (object silhouettes, not far ground).
    pub row_edge_px: Vec<u8>,
    /// Elevation of each row, radians (from the first scan).
    pub row_elevation_rad: Vec<f32>,
    /// Azimuth of each column, radians.
    pub column_azimuth_rad: Vec<f32>,
    /// Which scan of `scan_range_m` each pixel comes from.
    pub scan: Vec<u32>,
    /// Each scan's whole completed range image (row-major, left-out pixels included):
    /// the context of a pixel's column.
    pub scan_range_m: Vec<Vec<f32>>,
}

impl Pixels {
    pub fn collect(scans: &[ScanFeatures], reach_m: f32) -> Self {
        let mut px = Pixels {
            reach_m,
            ..Pixels::default()
        };
        if let Some(f) = scans.first() {
            px.height = f.height;
            px.width = f.width;
            px.row_elevation_rad = (0..f.height)
                .map(|i| f.elevation_rad.get(i * f.width).copied().unwrap_or(0.0))
                .collect();
            px.column_azimuth_rad = (0..f.width)
                .map(|j| f.azimuth_rad.get(j).copied().unwrap_or(0.0))
                .collect();
        }
        let ground_depth = ground_depth_m(scans).filter(|_| reach_m.is_finite());
        let open_above = open_elevation_rad(ground_depth, reach_m);
        let ceiling = ceiling_height_m(scans).filter(|_| reach_m.is_finite());
        for f in scans {
            if f.height != px.height || f.width != px.width {
                continue;
            }
            let scan = px.scan_range_m.len() as u32;
            px.scan_range_m.push(f.range_m.clone());
            let (enclosure, surface) = enclosures(f);
            let laser = laser_enclosures(f, &surface);
            let ground_r = match ground_depth {
                Some(h) => open_ground_range(f, &enclosure, open_above, h),
                None => vec![f32::NAN; f.len()],
            };
            let ceiling_r = match ceiling {
                Some(h) => ceiling_range(f, h, reach_m),
                None => vec![f32::NAN; f.len()],
            };
            for (k, &enclosure) in enclosure.iter().enumerate() {
                let (mut r, mut cos) = (f.range_m[k], f.incidence_rad[k].cos());
                let plane_r = if ground_r[k].is_finite() {
                    ground_r[k]
                } else {
                    ceiling_r[k]
                };
                let level_plane = plane_r.is_finite();
                if level_plane {
                    // The ray meets a level plane at cos(incidence) = |sin(e)|.
                    r = plane_r;
                    cos = f.elevation_rad[k].sin().abs();
                }
                if r > reach_m || (r.is_nan() && f.elevation_rad[k] > open_above) {
                    continue;
                }
                let row = f.row[k] as usize;
                px.row.push(row as u16);
                px.column.push((k % f.width.max(1)) as u16);
                px.range_m.push(r);
                px.cos_incidence.push(cos);
                px.class.push((f.class[k] & 0xffff) as u16);
                px.kept.push(f.kept[k]);
                px.enclosure_px.push(enclosure);
                px.surface_px.push(surface[k]);
                px.laser_px.push(laser[k]);
                px.level_plane.push(level_plane);
                px.edge_px
                    .push(f.edge_px.get(k).copied().unwrap_or(u8::MAX));
                px.row_edge_px
                    .push(f.row_edge_px.get(k).copied().unwrap_or(u8::MAX));
                px.scan.push(scan);
            }
        }
        px
    }

    pub fn len(&self) -> usize {
        self.kept.len()
    }

    pub fn is_empty(&self) -> bool {
        self.kept.is_empty()
    }

    pub fn drop_rate(&self) -> f64 {
        self.kept.iter().filter(|k| !**k).count() as f64 / self.len().max(1) as f64
    }
}

/// The sim's keep rate per (row, range cell, enclosed or not); the last range
/// cell holds pixels without geometry. Enclosed (neighbours return on both sides
/// within [`BASELINE_ENCLOSED_PX`]) splits a hole in a surface, which only
/// dropout makes, from the edge of open space, which the scene makes: one rate
/// for both would under-predict every surface pixel of rows that see much open
/// space, and a weak laser there would look like one that keeps too much. Times an azimuth factor per (row, sector) where the sim
/// keeps more or fewer of the sector's pixels than their cells predict beyond
/// doubt (|z| > 4: the sim's own blind spots), else 1.
#[derive(Debug, Clone, PartialEq)]
pub struct Baseline {
    cells: usize,
    keep: Vec<f64>,
    sectors: usize,
    width: usize,
    azimuth: Vec<f64>,
}

/// A pixel counts as enclosed for the baseline when its neighbours return within
/// this many pixels on both sides.
const BASELINE_ENCLOSED_PX: u8 = 3;

/// Azimuth sectors of the baseline's azimuth factor.
const BASELINE_SECTORS: usize = 64;

impl Baseline {
    fn sector(&self, px: &Pixels, i: usize) -> usize {
        px.row[i] as usize * self.sectors + px.column[i] as usize * self.sectors / self.width.max(1)
    }

    fn cell(&self, px: &Pixels, i: usize) -> usize {
        let r = px.range_m[i];
        let c = if r.is_finite() {
            ((r.max(0.0) / BASELINE_RANGE_BIN_M) as usize).min(self.cells - 2)
        } else {
            self.cells - 1
        };
        let e = usize::from(px.surface_px[i] <= BASELINE_ENCLOSED_PX);
        (px.row[i] as usize * self.cells + c) * 2 + e
    }

    pub fn from_sim(sim: &Pixels, reach_m: f32) -> Self {
        let finite_cells = if reach_m.is_finite() {
            (reach_m / BASELINE_RANGE_BIN_M) as usize + 1
        } else {
            80
        };
        let cells = finite_cells.clamp(1, 200) + 1;
        let rows = sim.height.max(1);
        let sectors = BASELINE_SECTORS.min(sim.width.max(1));
        let mut b = Baseline {
            cells,
            keep: Vec::new(),
            sectors,
            width: sim.width,
            azimuth: vec![1.0; rows * sectors],
        };
        // Cells are (row, range cell, enclosed or not); a cell's prior is its
        // (range cell, enclosed) rate over all rows.
        let mut n = vec![0f64; rows * cells * 2];
        let mut k = vec![0f64; rows * cells * 2];
        for i in 0..sim.len() {
            let c = b.cell(sim, i);
            n[c] += 1.0;
            k[c] += f64::from(u8::from(sim.kept[i]));
        }
        let global = 1.0 - sim.drop_rate();
        let across_rows = |i: usize| i % (cells * 2);
        let mut range_keep = vec![global; cells * 2];
        for (c, rk) in range_keep.iter_mut().enumerate() {
            let (nn, kk) = (0..rows).fold((0.0, 0.0), |(a, b), r| {
                (a + n[r * cells * 2 + c], b + k[r * cells * 2 + c])
            });
            *rk = (kk + SMOOTHING_PIXELS * global) / (nn + SMOOTHING_PIXELS);
        }
        b.keep = (0..rows * cells * 2)
            .map(|i| {
                (k[i] + SMOOTHING_PIXELS * range_keep[across_rows(i)]) / (n[i] + SMOOTHING_PIXELS)
            })
            .collect();
        // A sector departs where the sim keeps more or fewer of its pixels than
        // their (row, range) cells predict: a blind spot of the sim itself. Judged
        // against the cells, not the row's rate, so that a wall in one sector and
        // sky in the next (the scene) is no departure.
        let mut kept = vec![0f64; rows * sectors];
        let mut expected = vec![0f64; rows * sectors];
        let mut variance = vec![0f64; rows * sectors];
        for i in 0..sim.len() {
            let s = b.sector(sim, i);
            let p = b.keep[b.cell(sim, i)];
            kept[s] += f64::from(u8::from(sim.kept[i]));
            expected[s] += p;
            variance[s] += p * (1.0 - p);
        }
        for s in 0..rows * sectors {
            let z = (kept[s] - expected[s]) / variance[s].sqrt().max(1e-9);
            if expected[s] > 0.0 && z.abs() > 4.0 {
                b.azimuth[s] = kept[s] / expected[s];
            }
        }
        b
    }

    /// Baseline keep probability of every pixel of `px`.
    pub fn keep_of(&self, px: &Pixels) -> Vec<f64> {
        (0..px.len())
            .map(|i| {
                let a = self.azimuth.get(self.sector(px, i)).copied().unwrap_or(1.0);
                (self.keep.get(self.cell(px, i)).copied().unwrap_or(1.0) * a).min(1.0)
            })
            .collect()
    }
}

/// One fitted drop model: a drop probability per bin of its family.
#[derive(Debug, Clone, PartialEq)]
pub struct DropFit {
    pub drop_prob: Vec<f64>,
    /// Fitted parameters, as the report shows them.
    pub params: serde_json::Map<String, serde_json::Value>,
    /// The effect as physics-config entries (catalogue id -> parameters), so the
    /// fitted physics can be rendered.
    pub physics: serde_json::Map<String, serde_json::Value>,
    /// Number of free parameters (for the penalty).
    pub n_params: usize,
    /// Where the effect acts, in words.
    pub location: String,
}

/// A candidate drop model: which bin of its feature a pixel falls in, and how the
/// per-bin drop probabilities are fitted.
pub trait DropFamily: Sync {
    /// The catalogue id.
    fn id(&self) -> &'static str;
    /// Number of bins on this pixel set's grid.
    fn bins(&self, px: &Pixels) -> usize;
    /// Bin of pixel `i`, or None where the effect cannot act (unknown feature).
    fn bin(&self, px: &Pixels, i: usize) -> Option<usize>;
    /// Every pixel's bin: a family whose feature comes from a pixel's context computes
    /// it once per context here.
    fn bins_of(&self, px: &Pixels) -> Vec<Option<usize>> {
        (0..px.len()).map(|i| self.bin(px, i)).collect()
    }
    /// Maximum-likelihood fit given the pooled table (None: nothing to fit).
    fn fit(&self, table: &QTable, px: &Pixels) -> Option<DropFit>;
    /// Whether the effect acts the same in every direction (sensor physics
    /// does; scenes do not): then it must improve the held-out fit both ahead
    /// and behind the sensor to be claimed.
    fn azimuth_invariant(&self) -> bool {
        true
    }
    /// Whether other evidence already established the effect (motion from the
    /// seam's range step): then it is taken before the others wherever it beats
    /// its penalty, the others must explain what it leaves, and it is not removed
    /// as redundant with them.
    fn established(&self) -> bool {
        false
    }
}

/// Pixels pooled by (bin, level of `1 − q`), `q` the keep probability of the rest
/// of the model.
#[derive(Debug, Clone, PartialEq)]
pub struct QTable {
    pub bins: usize,
    /// The occupied (bin, level) cells, bin by bin, levels ascending: (kept,
    /// dropped, sum of q). Most of a bin's levels are empty, and the fits read
    /// each bin many times.
    cells: Vec<(f64, f64, f64)>,
    /// Where each bin's cells start in `cells` (and, last, where they end).
    starts: Vec<usize>,
    /// All pixels of the set (the NLL is per pixel of the whole set).
    pub pixels: f64,
}

fn q_level(q: f64) -> usize {
    let u = (1.0 - q).max(Q_FLOOR);
    let t = (u.ln() - Q_FLOOR.ln()) / -Q_FLOOR.ln();
    ((t * Q_LEVELS as f64) as usize).min(Q_LEVELS - 1)
}

impl QTable {
    pub fn build(family: &dyn DropFamily, px: &Pixels, rest_keep: &[f64]) -> Self {
        let bins = family.bins(px);
        let mut cells = vec![(0.0, 0.0, 0.0); bins * Q_LEVELS];
        let of = family.bins_of(px);
        for (i, &q) in rest_keep.iter().enumerate() {
            let Some(b) = of[i].filter(|&b| b < bins) else {
                continue;
            };
            let cell = &mut cells[b * Q_LEVELS + q_level(q)];
            if px.kept[i] {
                cell.0 += 1.0;
            } else {
                cell.1 += 1.0;
            }
            cell.2 += q;
        }
        let mut starts = Vec::with_capacity(bins + 1);
        let mut occupied = Vec::new();
        for bin in cells.chunks(Q_LEVELS) {
            starts.push(occupied.len());
            occupied.extend(bin.iter().filter(|c| c.0 + c.1 > 0.0));
        }
        starts.push(occupied.len());
        QTable {
            bins,
            cells: occupied,
            starts,
            pixels: px.len().max(1) as f64,
        }
    }

    fn cells_of(&self, b: usize) -> &[(f64, f64, f64)] {
        &self.cells[self.starts[b]..self.starts[b + 1]]
    }

    /// (kept, dropped) pixels of bin `b`.
    pub fn counts(&self, b: usize) -> (f64, f64) {
        self.cells_of(b)
            .iter()
            .fold((0.0, 0.0), |a, c| (a.0 + c.0, a.1 + c.1))
    }

    /// Total NLL (nats, not normalised) of bin `b` dropping with `p`.
    pub fn bin_nll(&self, b: usize, p: f64) -> f64 {
        let mut total = 0.0;
        for &(kept, dropped, qs) in self.cells_of(b) {
            let n = kept + dropped;
            let keep = (qs / n * (1.0 - p)).clamp(1e-12, KEEP_MAX);
            total -= kept * keep.ln() + dropped * (1.0 - keep).ln();
        }
        total
    }

    /// NLL per pixel of the whole set when bin `b` drops with `drop_prob[b]`
    /// (pixels outside every bin are left out: constant in the fit).
    pub fn nll(&self, drop_prob: &[f64]) -> f64 {
        (0..self.bins)
            .map(|b| self.bin_nll(b, drop_prob.get(b).copied().unwrap_or(0.0)))
            .sum::<f64>()
            / self.pixels
    }

    /// The drop probability in [0, 0.999] that minimises bin `b`'s NLL (convex:
    /// golden section).
    pub fn best_bin_prob(&self, b: usize) -> f64 {
        golden(0.0, 0.999, 40, |p| self.bin_nll(b, p)).0
    }
}

/// Golden-section minimum of `f` on [lo, hi]: (argmin, min).
pub fn golden(mut lo: f64, mut hi: f64, iters: usize, f: impl Fn(f64) -> f64) -> (f64, f64) {
    let g = (5f64.sqrt() - 1.0) / 2.0;
    for _ in 0..iters {
        let (m1, m2) = (hi - g * (hi - lo), lo + g * (hi - lo));
        if f(m1) <= f(m2) {
            hi = m2;
        } else {
            lo = m1;
        }
    }
    let x = 0.5 * (lo + hi);
    (x, f(x))
}

/// Per-pixel keep probability of a model: `c · baseline · Π (1 − p)`.
fn model_keep(
    px: &Pixels,
    baseline: &[f64],
    c: f64,
    effects: &[(&dyn DropFamily, &DropFit)],
) -> Vec<f64> {
    let mut keep: Vec<f64> = baseline.iter().map(|b| c * b).collect();
    for (family, fit) in effects {
        for (k, b) in keep.iter_mut().zip(family.bins_of(px)) {
            if let Some(b) = b {
                *k *= 1.0 - fit.drop_prob.get(b).copied().unwrap_or(0.0);
            }
        }
    }
    keep.iter().map(|k| k.clamp(1e-12, KEEP_MAX)).collect()
}

/// NLL of one pixel's kept/dropped state under keep probability `k`.
fn pixel_nll(kept: bool, k: f64) -> f64 {
    let k = k.clamp(1e-12, KEEP_MAX);
    if kept { -k.ln() } else { -(1.0 - k).ln() }
}

/// Mean per-pixel NLL of the kept/dropped masks under per-pixel keep probabilities.
pub fn mask_nll(px: &Pixels, keep: &[f64]) -> f64 {
    let total: f64 = px
        .kept
        .iter()
        .zip(keep)
        .map(|(&kept, &k)| pixel_nll(kept, k))
        .sum();
    total / px.len().max(1) as f64
}

/// Held-out NLL (nats, summed) of the pixels ahead of the sensor (|azimuth| <
/// 90 deg) and behind it, each side at its own overall rate (a shift of every
/// keep logit): whether an effect helps on both sides is a question about its
/// pattern. The one keep scale refitted beside an effect raises the keep rate of
/// every pixel the effect does not bin, and a side that sees mostly open space
/// would look worse although the effect fits it. A shift in logits, unlike a
/// scale, never saturates, so a side whose scenes keep far more than the sim's
/// still shows the pattern.
fn mask_nll_ahead_behind(px: &Pixels, keep: &[f64]) -> [f64; 2] {
    const BINS: usize = 448;
    const LIMIT: f64 = 28.0;
    // Per side and logit bin (0.125 wide): (kept, dropped, sum of logits), so the
    // shift is searched over a few hundred cells rather than every pixel.
    let mut cells = vec![[(0.0, 0.0, 0.0); BINS]; 2];
    for (i, (&kept, &k)) in px.kept.iter().zip(keep).enumerate() {
        let a = px
            .column_azimuth_rad
            .get(px.column[i] as usize)
            .copied()
            .unwrap_or(0.0);
        let side = usize::from(a.abs() > std::f32::consts::FRAC_PI_2);
        let k = k.clamp(1e-12, KEEP_MAX);
        let z = (k / (1.0 - k)).ln();
        let bin = (((z + LIMIT) / (2.0 * LIMIT) * BINS as f64) as usize).min(BINS - 1);
        let cell = &mut cells[side][bin];
        if kept {
            cell.0 += 1.0;
        } else {
            cell.1 += 1.0;
        }
        cell.2 += z;
    }
    [0, 1].map(|side| {
        let nll = |shift: f64| {
            cells[side]
                .iter()
                .filter(|c| c.0 + c.1 > 0.0)
                .map(|&(kept, dropped, zs)| {
                    let z = zs / (kept + dropped) + shift;
                    kept * bernoulli_nll(z, true) + dropped * bernoulli_nll(z, false)
                })
                .sum::<f64>()
        };
        golden(-8.0, 8.0, 48, nll).1
    })
}

/// The keep scale `c` minimising the NLL of `keep = c · rest` (pooled by level).
fn best_scale(px: &Pixels, rest: &[f64]) -> f64 {
    struct One;
    impl DropFamily for One {
        fn id(&self) -> &'static str {
            "scale"
        }
        fn bins(&self, _: &Pixels) -> usize {
            1
        }
        fn bin(&self, _: &Pixels, _: usize) -> Option<usize> {
            Some(0)
        }
        fn fit(&self, _: &QTable, _: &Pixels) -> Option<DropFit> {
            None
        }
    }
    let table = QTable::build(&One, px, rest);
    // keep = c·q = q·(1 − p) with p = 1 − c; c above 1 allowed (1 − p > 1).
    golden(0.3, 3.0, 48, |c| table.bin_nll(0, 1.0 - c)).0
}

/// One effect the selection kept, with its held-out numbers.
#[derive(Debug, Clone, PartialEq)]
pub struct Selected {
    pub id: &'static str,
    pub fit: DropFit,
    /// Held-out NLL per pixel of the model before this effect was added (c refitted).
    pub nll_without: f64,
    /// ... and with it.
    pub nll_with: f64,
    pub penalty: f64,
    /// Selection round (0 = strongest).
    pub round: usize,
}

impl Selected {
    pub fn gain(&self) -> f64 {
        self.nll_without - self.nll_with
    }
}

/// A candidate's result in the last round it was tried (for the report).
#[derive(Debug, Clone, PartialEq)]
pub struct Tried {
    pub id: &'static str,
    pub gain: f64,
    pub penalty: f64,
    pub n_params: usize,
}

/// The outcome of forward selection.
#[derive(Debug, Clone, PartialEq)]
pub struct DropSelection {
    pub selected: Vec<Selected>,
    /// Every candidate's held-out gain when first tried (round 0), strongest first.
    pub tried: Vec<Tried>,
    /// Held-out NLL per pixel: the sim as given (c = 1), the null (c fitted) and
    /// the final model.
    pub before_nll: f64,
    pub null_nll: f64,
    pub after_nll: f64,
    pub keep_scale: f64,
    /// Whether the keep scale was refitted beside the candidates (else held).
    pub scale_refitted: bool,
    pub test_pixels: usize,
}

/// Errors of a fit.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum FitError {
    #[error("no pixel within the sensor's reach in the {0} scans; nothing to fit")]
    NoPixels(&'static str),
}

/// The fitted model's per-pixel keep probability on `px` (for curves and maps).
pub fn keep_under(
    families: &[&dyn DropFamily],
    selection: &DropSelection,
    baseline: &Baseline,
    px: &Pixels,
) -> Vec<f64> {
    let base = baseline.keep_of(px);
    let effects: Vec<(&dyn DropFamily, &DropFit)> = selection
        .selected
        .iter()
        .filter_map(|s| {
            families
                .iter()
                .find(|f| f.id() == s.id)
                .map(|f| (*f, &s.fit))
        })
        .collect();
    model_keep(px, &base, selection.keep_scale, &effects)
}

/// Greedy forward selection of `families` (at most `max_effects`), then
/// backward elimination: an effect that no longer beats its penalty once the
/// others are refitted without it (a proxy chosen early, e.g. range for grazing
/// incidence on far ground) is removed and the selection rerun without it.
pub fn select(
    families: &[&dyn DropFamily],
    baseline: &Baseline,
    train: &Pixels,
    test: &Pixels,
    max_effects: usize,
) -> Result<DropSelection, FitError> {
    let mut allowed: Vec<&dyn DropFamily> = families.to_vec();
    let mut first_tried = None;
    loop {
        let mut selection = forward(&allowed, baseline, train, test, max_effects)?;
        let tried = first_tried.get_or_insert_with(|| selection.tried.clone());
        let redundant = redundant_effect(&allowed, &selection, baseline, train, test);
        match redundant {
            Some(id) => allowed.retain(|f| f.id() != id),
            None => {
                selection.tried = tried.clone();
                return Ok(selection);
            }
        }
    }
}

/// The selected effect whose removal (the others refitted in their order)
/// costs the least held-out NLL below its penalty, if any.
fn redundant_effect(
    families: &[&dyn DropFamily],
    selection: &DropSelection,
    baseline: &Baseline,
    train: &Pixels,
    test: &Pixels,
) -> Option<&'static str> {
    if selection.selected.len() < 2 {
        return None;
    }
    let base_train = baseline.keep_of(train);
    let base_test = baseline.keep_of(test);
    let family = |id: &str| families.iter().copied().find(|f| f.id() == id);
    selection
        .selected
        .iter()
        .filter(|drop| family(drop.id).is_some_and(|f| !f.established()))
        .filter_map(|drop| {
            let mut c = selection.keep_scale;
            let mut fits: Vec<(&dyn DropFamily, DropFit)> = Vec::new();
            for s in selection.selected.iter().filter(|s| s.id != drop.id) {
                let f = family(s.id)?;
                let given: Vec<(&dyn DropFamily, &DropFit)> =
                    fits.iter().map(|(f, d)| (*f, d)).collect();
                let (fit, c_fit) =
                    fit_given(f, train, &base_train, c, &given, selection.scale_refitted)?;
                c = c_fit;
                fits.push((f, fit));
            }
            let given: Vec<(&dyn DropFamily, &DropFit)> =
                fits.iter().map(|(f, d)| (*f, d)).collect();
            let without = mask_nll(test, &model_keep(test, &base_test, c, &given));
            let loss = without - selection.after_nll;
            (loss < drop.penalty).then_some((drop.id, loss - drop.penalty))
        })
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .map(|(id, _)| id)
}

/// Greedy forward selection of `families` (at most `max_effects`).
fn forward(
    families: &[&dyn DropFamily],
    baseline: &Baseline,
    train: &Pixels,
    test: &Pixels,
    max_effects: usize,
) -> Result<DropSelection, FitError> {
    if train.is_empty() {
        return Err(FitError::NoPixels("training"));
    }
    if test.is_empty() {
        return Err(FitError::NoPixels("held-out"));
    }
    let base_train = baseline.keep_of(train);
    let base_test = baseline.keep_of(test);
    let before_nll = mask_nll(test, &model_keep(test, &base_test, 1.0, &[]));
    // The null (only the overall rate differs) is adopted only where it beats
    // the sim as given on held-out scans. The scale may still be refitted beside
    // an effect: a sim whose overall rate was matched to the real one (its uniform
    // dropout raised) keeps too few of the pixels the effect spares, and only a
    // scale above 1 says so. An effect is judged against the better of the sim as
    // given and the null, so the scale's own gain is never credited to it.
    let c_null = best_scale(train, &base_train);
    let scale_only_nll = mask_nll(test, &model_keep(test, &base_test, c_null, &[]));
    let (mut c, null_nll) = if before_nll - scale_only_nll > MIN_GAIN_NATS {
        (c_null, scale_only_nll)
    } else {
        (1.0, before_nll)
    };
    // Where the scale alone fits the held-out scans clearly worse than the sim as
    // given, the training scenes drop more or fewer rays than the held-out ones, and
    // a scale refitted beside a candidate would cost it that loss.
    let refit_scale = scale_only_nll - before_nll < MIN_GAIN_NATS;
    let n = train.len() as f64;
    let mut chosen: Vec<(usize, DropFit, Selected)> = Vec::new();
    let mut current_nll = before_nll.min(scale_only_nll);
    let mut current_halves = mask_nll_ahead_behind(test, &model_keep(test, &base_test, c, &[]));
    let mut tried = Vec::new();
    for round in 0..max_effects {
        let effects: Vec<(&dyn DropFamily, &DropFit)> =
            chosen.iter().map(|(i, f, _)| (families[*i], f)).collect();
        let mut viable: Vec<Candidate> = Vec::new();
        for (fi, family) in families.iter().enumerate() {
            if chosen.iter().any(|(i, ..)| *i == fi) {
                continue;
            }
            let Some((at_scale, refit)) =
                fit_both(*family, train, &base_train, c, &effects, refit_scale)
            else {
                continue;
            };
            let held_out = |fit: &DropFit, c: f64| {
                let mut with = effects.clone();
                with.push((*family, fit));
                let keep = model_keep(test, &base_test, c, &with);
                (mask_nll(test, &keep), keep)
            };
            // A scale refitted beside a candidate can run past certainty where the
            // baseline keeps most (the keep is clamped there, and each held-out drop
            // in such a pixel costs 16 nats). Where the candidate fitted at the
            // current scale fits the held-out scans better by more than the floor,
            // the refit broke it, and the fit at the current scale is judged.
            let (fit, c_fit, (nll, keep)) = match refit {
                Some((fit, c_fit)) if c_fit != c => {
                    let refitted = held_out(&fit, c_fit);
                    let fixed = held_out(&at_scale, c);
                    if fixed.0 < refitted.0 - MIN_GAIN_NATS {
                        (at_scale, c, fixed)
                    } else {
                        (fit, c_fit, refitted)
                    }
                }
                refit => {
                    let (fit, c_fit) = refit.unwrap_or((at_scale, c));
                    let judged = held_out(&fit, c_fit);
                    (fit, c_fit, judged)
                }
            };
            let halves = mask_nll_ahead_behind(test, &keep);
            let penalty = (fit.n_params as f64 * n.ln() / (2.0 * n)).max(MIN_GAIN_NATS);
            // A direction-invariant effect that helps only on one side of the
            // sensor is the scenes' difference, not physics: no gain.
            let one_sided =
                family.azimuth_invariant() && (0..2).any(|h| halves[h] >= current_halves[h]);
            let gain = if one_sided {
                (current_nll - nll).min(0.0)
            } else {
                current_nll - nll
            };
            if round == 0 {
                tried.push(Tried {
                    id: family.id(),
                    gain,
                    penalty,
                    n_params: fit.n_params,
                });
            }
            let margin = gain - penalty;
            if margin > 0.0 {
                viable.push(Candidate {
                    family: fi,
                    fit,
                    nll,
                    penalty,
                    c_fit,
                    halves,
                    margin,
                });
            }
        }
        let Some(best) = strongest(&viable, families) else {
            break;
        };
        let explains = |rival: &Candidate| {
            let mut given = effects.clone();
            given.push((families[rival.family], &rival.fit));
            let Some((fit, c_both)) = fit_given(
                families[best.family],
                train,
                &base_train,
                rival.c_fit,
                &given,
                refit_scale,
            ) else {
                return true;
            };
            given.push((families[best.family], &fit));
            let both = mask_nll(test, &model_keep(test, &base_test, c_both, &given));
            rival.nll - both < best.penalty
        };
        let best = simpler_rival(best, &viable, families, explains)
            .unwrap_or(best)
            .clone();
        chosen.push((
            best.family,
            best.fit.clone(),
            Selected {
                id: families[best.family].id(),
                fit: best.fit,
                nll_without: current_nll,
                nll_with: best.nll,
                penalty: best.penalty,
                round,
            },
        ));
        current_nll = best.nll;
        current_halves = best.halves;
        c = best.c_fit;
    }
    tried.sort_by(|a, b| (b.gain - b.penalty).total_cmp(&(a.gain - a.penalty)));
    Ok(DropSelection {
        selected: chosen.into_iter().map(|(.., s)| s).collect(),
        tried,
        before_nll,
        null_nll,
        after_nll: current_nll,
        keep_scale: c,
        scale_refitted: refit_scale,
        test_pixels: test.len(),
    })
}

/// A candidate effect of one selection round that beats its penalty.
#[derive(Clone)]
struct Candidate {
    family: usize,
    fit: DropFit,
    /// Held-out NLL per pixel with the effect.
    nll: f64,
    penalty: f64,
    c_fit: f64,
    halves: [f64; 2],
    /// Held-out gain over the penalty.
    margin: f64,
}

/// The round's strongest candidate: established families first, then by margin.
fn strongest<'a>(viable: &'a [Candidate], families: &[&dyn DropFamily]) -> Option<&'a Candidate> {
    viable.iter().reduce(|best, c| {
        let (e, eb) = (
            families[c.family].established(),
            families[best.family].established(),
        );
        let better = if e != eb { e } else { c.margin > best.margin };
        if better { c } else { best }
    })
}

/// A candidate with fewer parameters than `best` that fits nearly as well (margins within
/// [`MIN_GAIN_NATS`], the scale of what scene differences alone produce) and leaves `best`
/// nothing to add (`explains`): the two read the same drops, and the simpler reading is
/// named. A free rate per range band of depth edges can trace a range curve that thins the
/// far field, where the range curve itself is the physics.
fn simpler_rival<'a>(
    best: &'a Candidate,
    viable: &'a [Candidate],
    families: &[&dyn DropFamily],
    explains: impl Fn(&Candidate) -> bool,
) -> Option<&'a Candidate> {
    let established = families[best.family].established();
    let mut rivals: Vec<&Candidate> = viable
        .iter()
        .filter(|c| {
            c.family != best.family
                && families[c.family].established() == established
                && c.fit.n_params < best.fit.n_params
                && best.margin - c.margin < MIN_GAIN_NATS
        })
        .collect();
    rivals.sort_by(|a, b| b.margin.total_cmp(&a.margin));
    rivals.into_iter().find(|c| explains(c))
}

/// Fits `family` on `train` given the chosen `effects` at the keep scale `c0`, or,
/// with `refit_scale`, alternating with the scale: (fit, scale).
fn fit_given(
    family: &dyn DropFamily,
    train: &Pixels,
    base: &[f64],
    c0: f64,
    effects: &[(&dyn DropFamily, &DropFit)],
    refit_scale: bool,
) -> Option<(DropFit, f64)> {
    let (at_scale, refit) = fit_both(family, train, base, c0, effects, refit_scale)?;
    Some(refit.unwrap_or((at_scale, c0)))
}

/// [`fit_given`]'s fit at the scale `c0`, and with `refit_scale` the fit alternated with
/// the scale (fit, scale); None where a fit fails.
fn fit_both(
    family: &dyn DropFamily,
    train: &Pixels,
    base: &[f64],
    c0: f64,
    effects: &[(&dyn DropFamily, &DropFit)],
    refit_scale: bool,
) -> Option<(DropFit, Option<(DropFit, f64)>)> {
    let rest_unit = model_keep(train, base, 1.0, effects);
    let fit_at = |c: f64| {
        let rest: Vec<f64> = rest_unit
            .iter()
            .map(|k| (k * c).clamp(1e-12, KEEP_MAX))
            .collect();
        family.fit(&QTable::build(family, train, &rest), train)
    };
    let scale_beside = |fit: &DropFit| {
        let with_effect: Vec<f64> = family
            .bins_of(train)
            .into_iter()
            .zip(&rest_unit)
            .map(|(b, rest)| {
                let p = b.and_then(|b| fit.drop_prob.get(b)).copied().unwrap_or(0.0);
                rest * (1.0 - p)
            })
            .collect();
        best_scale(train, &with_effect)
    };
    let at_scale = fit_at(c0)?;
    if !refit_scale {
        return Some((at_scale, None));
    }
    let fit = fit_at(scale_beside(&at_scale))?;
    let c = scale_beside(&fit);
    Some((at_scale, Some((fit, c))))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A scan of level ground 1.5 m down, rows 1 deg apart from -1 deg down, 64
    /// columns; the rows looking farther than `dropped_beyond_m` lost their rays,
    /// and the fill copied the nearest return's range into them.
    fn far_ground_dropped(rows: usize, dropped_beyond_m: f32) -> ScanFeatures {
        let elevation = |i: usize| -(1.0 + i as f32).to_radians();
        let nearest_kept = (0..rows)
            .map(|i| 1.5 / (-elevation(i)).sin())
            .find(|&r| r <= dropped_beyond_m)
            .unwrap_or(f32::NAN);
        level_rows(rows, |i| {
            let e = elevation(i);
            let r = 1.5 / (-e).sin();
            let kept = r <= dropped_beyond_m;
            let range = if kept { r } else { nearest_kept };
            (e, kept, range, std::f32::consts::FRAC_PI_2 + e)
        })
    }

    /// Rows looking up 15 deg to 1 deg under a ceiling 1.5 m above the sensor, 64
    /// columns; rays meeting it farther than 15 m lost their returns (grazing), and
    /// the fill copied a far wall's 40 m into them.
    fn ceiling_grazing_dropped() -> ScanFeatures {
        level_rows(15, |i| {
            let e = (15.0 - i as f32).to_radians();
            let r = 1.5 / e.sin();
            let kept = r <= 15.0;
            (e, kept, if kept { r } else { 40.0 }, 0.3)
        })
    }

    /// A scan of 64 columns whose every row `i` is the same all round:
    /// `row(i)` = (elevation, kept, range, incidence).
    fn level_rows(rows: usize, row: impl Fn(usize) -> (f32, bool, f32, f32)) -> ScanFeatures {
        let w = 64;
        let mut f = ScanFeatures::empty(rows, w);
        for i in 0..rows {
            let (e, kept, range, incidence) = row(i);
            for j in 0..w {
                f.row.push(i as u32);
                f.azimuth_rad
                    .push(j as f32 * std::f32::consts::TAU / w as f32);
                f.elevation_rad.push(e);
                f.range_m.push(range);
                f.incidence_rad.push(incidence);
                f.edge_px.push(8);
                f.row_edge_px.push(8);
                f.class.push(0);
                f.kept.push(kept);
            }
        }
        f
    }

    #[test]
    fn a_level_ceiling_completes_the_upward_rows_that_grazing_drops_emptied() {
        let mut f = ceiling_grazing_dropped();
        assert!((ceiling_height_m(std::slice::from_ref(&f)).unwrap() - 1.5).abs() < 1e-3);
        // A pillar 12 m away in column 3, seen by the lowest row: the rays above it
        // whose ceiling point lies beyond 12 m hit the pillar, not the ceiling.
        let k = 14 * f.width + 3;
        f.kept[k] = true;
        f.range_m[k] = 12.0 / f.elevation_rad[k].cos();
        let ceiling = ceiling_range(&f, 1.5, 60.0);
        for (k, &c) in ceiling.iter().enumerate() {
            let e = f.elevation_rad[k];
            let beyond_pillar = k % f.width == 3 && 1.5 / e.tan() >= 12.0;
            if f.kept[k] || beyond_pillar || 1.5 / e.sin() > 60.0 {
                assert!(c.is_nan(), "pixel {k}: {c}");
            } else {
                assert!((c - 1.5 / e.sin()).abs() < 1e-3, "pixel {k}: {c}");
            }
        }
        // The completed pixels reach the fit as grazing ceiling, not as the wall.
        let px = Pixels::collect(std::slice::from_ref(&f), 60.0);
        let plane: Vec<usize> = (0..px.len()).filter(|&i| px.level_plane[i]).collect();
        assert!(!plane.is_empty());
        for i in plane {
            let e = px.row_elevation_rad[px.row[i] as usize];
            assert!(!px.kept[i] && px.range_m[i] > 15.0);
            assert!(
                (px.range_m[i] * e.sin() - 1.5).abs() < 1e-3,
                "{}",
                px.range_m[i]
            );
            assert!(px.cos_incidence[i] < 0.1);
        }

        // In the open, upward returns spread over trees and facades: no ceiling.
        let mut open = ceiling_grazing_dropped();
        for k in (0..open.len()).filter(|&k| open.kept[k]) {
            let height = 0.5 + (k % 37) as f32 * 0.3;
            open.range_m[k] = height / open.elevation_rad[k].sin();
        }
        assert_eq!(ceiling_height_m(std::slice::from_ref(&open)), None);
    }

    #[test]
    fn open_ground_takes_the_level_grounds_range_where_nothing_stands_in_front() {
        let f = far_ground_dropped(30, 20.0);
        let enclosure = enclosures(&f).0;
        let open_above = -(3.0f32).to_radians();
        let ground = open_ground_range(&f, &enclosure, open_above, 1.5);
        for (k, &g) in ground.iter().enumerate() {
            let e = f.elevation_rad[k];
            let far = !f.kept[k] && enclosure[k] > ENCLOSED_PX;
            if far && e <= open_above {
                assert!((g - 1.5 / (-e).sin()).abs() < 1e-3, "pixel {k}: {g}");
            } else {
                assert!(g.is_nan(), "pixel {k}: {g}");
            }
        }
        assert!(ground.iter().any(|g| g.is_finite()));

        // Grazing drops that empty the ground from 8 m on leave its columns nothing
        // farther to see: what they lost is still the level ground.
        let near = far_ground_dropped(30, 8.0);
        let ground = open_ground_range(&near, &enclosures(&near).0, open_above, 1.5);
        let lost =
            (0..near.len()).filter(|&k| !near.kept[k] && near.elevation_rad[k] <= open_above);
        for k in lost {
            let e = near.elevation_rad[k];
            assert!(
                (ground[k] - 1.5 / (-e).sin()).abs() < 1e-3,
                "pixel {k}: {}",
                ground[k]
            );
        }

        // A wall 10 m away across the top rows of column 5 stands in front of the
        // far ground below it: that column keeps the fill's range.
        let mut walled = f.clone();
        for i in 0..3 {
            let k = i * walled.width + 5;
            walled.kept[k] = true;
            walled.range_m[k] = 10.0 / walled.elevation_rad[k].cos();
        }
        // A return 50 m away in column 7 shows the column saw past the lost
        // pixels' ground points: they are not open ground either.
        let k = 7;
        walled.kept[k] = true;
        walled.range_m[k] = 50.0 / walled.elevation_rad[k].cos();
        let open = vec![ENCLOSURE_CAP_PX; walled.len()];
        let ground = open_ground_range(&walled, &open, open_above, 1.5);
        for j in [5, 7] {
            assert!((0..walled.height).all(|i| ground[i * walled.width + j].is_nan()));
        }
        assert!((0..walled.height).any(|i| ground[i * walled.width + 6].is_finite()));

        // The open ground's pixels reach the range family's bins with their ground range.
        let px = Pixels::collect(std::slice::from_ref(&f), 60.0);
        assert!(px.level_plane.iter().any(|&o| o));
        for i in (0..px.len()).filter(|&i| px.level_plane[i]) {
            assert!(!px.kept[i] && px.range_m[i] > 20.0);
            assert!(
                (px.cos_incidence[i] - px.row_elevation_rad[px.row[i] as usize].abs().sin()).abs()
                    < 1e-4
            );
        }
    }

    #[test]
    fn q_table_nll_of_the_true_rate_is_the_binary_entropy() {
        struct Halves;
        impl DropFamily for Halves {
            fn id(&self) -> &'static str {
                "halves"
            }
            fn bins(&self, _: &Pixels) -> usize {
                2
            }
            fn bin(&self, _: &Pixels, i: usize) -> Option<usize> {
                Some(i % 2)
            }
            fn fit(&self, _: &QTable, _: &Pixels) -> Option<DropFit> {
                None
            }
        }
        let px = Pixels {
            kept: (0..400).map(|i| (i / 2) % 4 != 0).collect(),
            ..Default::default()
        };
        let table = QTable::build(&Halves, &px, &vec![1.0; 400]);
        let p = 0.25f64;
        let entropy = -(p * p.ln() + (1.0 - p) * (1.0 - p).ln());
        assert!((table.nll(&[0.25, 0.25]) - entropy).abs() < 1e-9);
        assert!(table.nll(&[0.5, 0.5]) > entropy);
        assert!((table.best_bin_prob(0) - 0.25).abs() < 1e-4);
        assert!((mask_nll(&px, &[0.75; 400]) - entropy).abs() < 1e-9);
        assert_eq!(table.counts(1), (150.0, 50.0));
    }

    #[test]
    fn golden_finds_a_parabola_minimum() {
        let (x, fx) = golden(-3.0, 5.0, 60, |x| (x - 1.25) * (x - 1.25) + 2.0);
        assert!((x - 1.25).abs() < 1e-6 && (fx - 2.0).abs() < 1e-9);
    }

    /// One row of 64 sectors x 16 columns: a wall 10 m away in the first half,
    /// nothing (no geometry, all dropped) in the second; `kept(column)` says
    /// which wall pixels the sim kept.
    fn wall_then_sky(kept: impl Fn(usize) -> bool) -> Pixels {
        let w = 64 * 16;
        let mut px = Pixels {
            height: 1,
            width: w,
            ..Pixels::default()
        };
        for j in 0..w {
            let wall = j < w / 2;
            px.row.push(0);
            px.column.push(j as u16);
            px.range_m.push(if wall { 10.0 } else { f32::NAN });
            px.kept.push(wall && kept(j));
            let enclosure = if wall { 1 } else { ENCLOSURE_CAP_PX };
            px.enclosure_px.push(enclosure);
            px.surface_px.push(enclosure);
        }
        px
    }

    #[test]
    fn baseline_tells_holes_in_a_surface_from_the_edge_of_open_space() {
        // A wall 10 m away whose rays return 19 in 20 times, then pixels beside
        // open space that the fill gave the wall's range, all dropped.
        let w = 1000;
        let mut px = Pixels {
            height: 1,
            width: w,
            ..Pixels::default()
        };
        for j in 0..w {
            let wall = j < 800;
            px.row.push(0);
            px.column.push(j as u16);
            px.range_m.push(10.0);
            px.kept.push(wall && j % 20 != 0);
            let enclosure = if wall { 1 } else { ENCLOSURE_CAP_PX };
            px.enclosure_px.push(enclosure);
            px.surface_px.push(enclosure);
        }
        let keep = Baseline::from_sim(&px, 50.0).keep_of(&px);
        assert!((keep[1] - 0.95).abs() < 0.01, "wall {}", keep[1]);
        assert!(keep[900] < 0.05, "open edge {}", keep[900]);
    }

    #[test]
    fn a_kept_pixels_enclosure_is_read_from_its_neighbours() {
        // One row: returns in columns 0, 2 and 4, then open space.
        let mut f = level_rows(1, |_| (0.0, true, 10.0, 0.0));
        for j in 0..64 {
            f.kept[j] = j <= 4 && j % 2 == 0;
        }
        let e = enclosures(&f).0;
        assert_eq!(e[1], 1, "a hole between two returns");
        assert_eq!(e[2], 2, "a return between returns two pixels away");
        assert_eq!(e[4], ENCLOSURE_CAP_PX, "a return beside open space");
    }

    #[test]
    fn a_gap_between_two_surfaces_is_not_a_hole_in_one() {
        // One row: a crown 10 m away (columns 0-9), open sky (10-11), another crown
        // 14 m away (12-20), a hole in it (21), the crown again (22-30).
        let mut f = level_rows(1, |_| (0.0, true, 10.0, 0.0));
        for j in 0..64 {
            f.kept[j] = j <= 30 && !matches!(j, 10 | 11 | 21);
            f.range_m[j] = if j < 12 { 10.0 } else { 14.0 };
        }
        let (any, surface) = enclosures(&f);
        assert_eq!((any[10], any[21]), (2, 1), "both enclosed by returns");
        assert_eq!(surface[10], ENCLOSURE_CAP_PX, "the sky between the crowns");
        assert_eq!(surface[21], 1, "the hole in the far crown");
    }

    #[test]
    fn a_dead_laser_over_the_ground_of_a_sparse_sensor_is_a_hole_in_it() {
        // Three rows 2 deg apart looking down at the ground 2 m below: their ground
        // points lie 9.6, 11.4 and 14.2 m away (inverse ranges 30 % apart), one height.
        // The middle laser is dead all round.
        let elevation = |i: usize| -(12.0f32 - 2.0 * i as f32).to_radians();
        let mut f = level_rows(3, |i| {
            let e = elevation(2 - i);
            (e, i != 1, 2.0 / -e.sin(), 0.0)
        });
        let (any, surface) = enclosures(&f);
        assert_eq!(
            (any[64 + 5], surface[64 + 5]),
            (1, 1),
            "the ground above and below"
        );
        // A wall 20 m away above the dead row and the ground below it: two surfaces.
        for j in 0..64 {
            f.range_m[j] = 20.0 / elevation(2).cos();
        }
        assert_eq!(
            enclosures(&f).1[64 + 5],
            ENCLOSURE_CAP_PX,
            "a wall above, the ground below"
        );
    }

    #[test]
    fn a_dead_bottom_laser_under_the_ground_is_a_hole_in_it() {
        // Three rows 2 deg apart looking down at the ground 2 m below; the bottom laser
        // is dead all round. Nothing lies below it, but the ground above runs on under it.
        let elevation = |i: usize| -(8.0f32 + 2.0 * i as f32).to_radians();
        let mut f = level_rows(3, |i| {
            let e = elevation(i);
            (e, i != 2, 2.0 / -e.sin(), 0.0)
        });
        let bottom = 2 * 64 + 5;
        let laser = |f: &ScanFeatures| laser_enclosures(f, &enclosures(f).1)[bottom];
        assert_eq!(enclosures(&f).1[bottom], ENCLOSURE_CAP_PX, "nothing below");
        assert_eq!(laser(&f), 1, "the ground above");
        f.kept[bottom] = true;
        assert_eq!(
            laser(&f),
            1,
            "a kept pixel there too: read from the returns above only"
        );
        // A wall 20 m away over the bottom row: not the ground.
        for k in 0..2 * 64 {
            f.range_m[k] = 20.0 / f.elevation_rad[k].cos();
        }
        assert_eq!(laser(&f), ENCLOSURE_CAP_PX, "a wall above");
    }

    #[test]
    fn the_horizon_between_a_ceiling_and_a_floor_is_not_enclosed() {
        // A garage's corridor: the top row meets the ceiling 1.2 m above, the bottom
        // row the floor 1.6 m below, and the row between them, just above the horizon,
        // reaches neither within range: open space, whatever lies above and below.
        let rows = [(1.4f32, 1.2f32), (0.4, f32::NAN), (-1.3, -1.6)];
        let f = level_rows(3, |i| {
            let (e_deg, z) = rows[i];
            let e = e_deg.to_radians();
            (
                e,
                !z.is_nan(),
                if z.is_nan() { 200.0 } else { z / e.sin() },
                0.0,
            )
        });
        let (any, surface) = enclosures(&f);
        assert_eq!(
            (any[64 + 5], surface[64 + 5]),
            (ENCLOSURE_CAP_PX, ENCLOSURE_CAP_PX)
        );
        // A wall 20 m away across the same rows encloses it: a hole in one surface.
        let f = level_rows(3, |i| {
            let e = rows[i].0.to_radians();
            (e, i != 1, 20.0 / e.cos(), 0.0)
        });
        let (any, surface) = enclosures(&f);
        assert_eq!((any[64 + 5], surface[64 + 5]), (1, 1));
    }

    #[test]
    fn of_two_readings_of_the_same_drops_the_simpler_is_named() {
        use crate::diagnose::drop::{EdgeFamily, RangeFamily};
        let families: [&dyn DropFamily; 2] = [&EdgeFamily, &RangeFamily];
        let candidate = |family: usize, n_params: usize, margin: f64| Candidate {
            family,
            fit: DropFit {
                drop_prob: vec![],
                params: serde_json::Map::new(),
                physics: serde_json::Map::new(),
                n_params,
                location: String::new(),
            },
            nll: 0.0,
            penalty: MIN_GAIN_NATS,
            c_fit: 1.0,
            halves: [0.0; 2],
            margin,
        };
        // Free edge rates per range band fit a little better than the range curve.
        let viable = [candidate(0, 16, 0.0046), candidate(1, 2, 0.0033)];
        let best = strongest(&viable, &families).unwrap();
        assert_eq!(best.family, 0);
        let rival = simpler_rival(best, &viable, &families, |_| true);
        assert_eq!(
            rival.map(|c| c.family),
            Some(1),
            "the range curve explains the edges away"
        );
        assert!(
            simpler_rival(best, &viable, &families, |_| false).is_none(),
            "edges add to it"
        );
        // Far apart, the better fit is the answer.
        let apart = [
            candidate(0, 16, 0.0046 + MIN_GAIN_NATS),
            candidate(1, 2, 0.0033),
        ];
        assert!(simpler_rival(&apart[0], &apart, &families, |_| true).is_none());
    }

    #[test]
    fn azimuth_factor_marks_the_sims_blind_spots_not_its_open_sky() {
        // The wall keeps 9 of 10 rays everywhere: no sector departs from its
        // cells, although half the row is sky.
        let even = Baseline::from_sim(&wall_then_sky(|j| j % 10 != 0), 50.0);
        assert!(even.azimuth.iter().all(|a| *a == 1.0), "{:?}", even.azimuth);
        // The sim drops every ray in sectors 8-11 of the wall: those, only.
        let blind = Baseline::from_sim(
            &wall_then_sky(|j| j % 10 != 0 && !(128..192).contains(&j)),
            50.0,
        );
        for (s, a) in blind.azimuth.iter().enumerate() {
            assert_eq!(*a < 0.5, (8..12).contains(&s), "sector {s}: {a}");
        }
    }

    /// Two rows of 400 columns spanning all azimuths; `kept(row, ahead, column)`
    /// says which pixels kept their rays.
    fn two_rows(kept: impl Fn(usize, bool, usize) -> bool) -> Pixels {
        let w = 400;
        let mut px = Pixels {
            height: 2,
            width: w,
            column_azimuth_rad: (0..w)
                .map(|j| (j as f32 / w as f32 - 0.5) * std::f32::consts::TAU)
                .collect(),
            ..Pixels::default()
        };
        for i in 0..2 {
            for j in 0..w {
                let ahead = px.column_azimuth_rad[j].abs() <= std::f32::consts::FRAC_PI_2;
                px.row.push(i as u16);
                px.column.push(j as u16);
                px.range_m.push(10.0);
                px.kept.push(kept(i, ahead, j));
            }
        }
        px
    }

    #[test]
    fn each_side_is_judged_at_its_own_overall_rate() {
        // Ahead keeps 9 of 10 rays, behind 1 of 2: a model that only moves the
        // overall rate is neither better nor worse on either side.
        let px = two_rows(|_, ahead, j| if ahead { j % 10 != 0 } else { j % 2 == 0 });
        let [ahead_low, behind_low] = mask_nll_ahead_behind(&px, &vec![0.6; px.len()]);
        let [ahead_high, behind_high] = mask_nll_ahead_behind(&px, &vec![0.8; px.len()]);
        assert!(
            (ahead_low - ahead_high).abs() < 1e-6 * ahead_low,
            "{ahead_low} {ahead_high}"
        );
        assert!(
            (behind_low - behind_high).abs() < 1e-6 * behind_low,
            "{behind_low} {behind_high}"
        );
        // A per-row pattern true ahead only (row 0 drops half, row 1 nothing;
        // behind both rows drop a quarter) helps ahead and not behind.
        let px = two_rows(|i, ahead, j| match (ahead, i) {
            (true, 0) => j % 2 == 0,
            (true, _) => true,
            (false, _) => j % 4 != 0,
        });
        let flat = mask_nll_ahead_behind(&px, &vec![0.75; px.len()]);
        let pattern: Vec<f64> = px
            .row
            .iter()
            .map(|&i| if i == 0 { 0.5 } else { 0.99 })
            .collect();
        let rows = mask_nll_ahead_behind(&px, &pattern);
        assert!(rows[0] < flat[0], "ahead {rows:?} {flat:?}");
        assert!(rows[1] >= flat[1], "behind {rows:?} {flat:?}");
    }

    #[test]
    fn no_pixels_is_an_error_not_a_panic() {
        let b = Baseline::from_sim(&Pixels::default(), 50.0);
        assert_eq!(
            select(&[], &b, &Pixels::default(), &Pixels::default(), 2),
            Err(FitError::NoPixels("training"))
        );
    }
}
