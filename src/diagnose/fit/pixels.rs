//! The pixels a fit uses ([`Pixels`]), pooled over scans within the sim's reach
//! ([`reach_m`]): each with its features, its enclosure by returns, and, where a level
//! plane explains a drop, that plane's range and incidence.

#[cfg(doc)]
use super::ENCLOSURE_CAP_PX;
#[cfg(doc)]
use super::enclosure::SURFACE_TOLERANCE;
use super::enclosure::{enclosures, laser_enclosures};
use super::level_plane::{
    ceiling_height_m, ceiling_range, ground_depth_m, open_elevation_rad, open_ground_range,
};
use crate::diagnose::features::ScanFeatures;

/// Pixels completed to near the sensor's reach are ambiguous: "no surface within
/// reach" (scene) or "dropped" (physics); their share depends on the scene, so
/// the fit leaves out completed ranges above `REACH_FRACTION` times the sim's
/// `REACH_QUANTILE` quantile of kept ranges.
pub const REACH_QUANTILE: f64 = 0.995;
pub const REACH_FRACTION: f32 = 0.85;

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
                if r > reach_m || (r.is_nan() && f.elevation_rad[k] > open_above) || f.in_gap(k) {
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
