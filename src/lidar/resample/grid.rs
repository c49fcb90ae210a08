//! Angle grids resized to another H x W (bilinear on (cos, sin) pairs, circular
//! columns, extrapolated rows), and sensor profiles resampled to another beam and
//! column count.

use super::source_coord;
use crate::lidar::{AngleGrid, SensorProfile};

/// Bilinear interpolation of unit vectors `(cos a, sin a)` of an angle field given
/// at four corners (top-left, top-right, bottom-left, bottom-right), returning the
/// angle. `t` runs along rows, `s` along columns; weights may fall outside [0, 1]
/// (row extrapolation).
fn lerp_angle(a: [(f32, f32); 4], t: f32, s: f32) -> f32 {
    let w = [(1.0 - t) * (1.0 - s), (1.0 - t) * s, t * (1.0 - s), t * s];
    let (mut c, mut si) = (0.0f32, 0.0f32);
    for ((ck, sk), wk) in a.iter().zip(w) {
        c += wk * ck;
        si += wk * sk;
    }
    si.atan2(c)
}

impl AngleGrid {
    /// The grid resampled to `height x width` (see the module doc for alignment).
    ///
    /// Elevation and azimuth are both interpolated bilinearly as (cos, sin) pairs.
    /// Columns are circular (the last column's neighbour is column 0). Rows are not:
    /// above the top row and below the bottom row the two outermost rows are
    /// extrapolated linearly, so a uniform elevation table stays uniform when
    /// upsampled (clamping would repeat the edge elevation).
    pub fn resized(&self, height: usize, width: usize) -> AngleGrid {
        let (h, w) = (self.height, self.width);
        let mut elevation_rad = Vec::with_capacity(height * width);
        let mut azimuth_rad = Vec::with_capacity(height * width);
        if h == 0 || w == 0 || self.elevation_rad.len() < h * w || self.azimuth_rad.len() < h * w {
            return AngleGrid {
                height: 0,
                width: 0,
                elevation_rad,
                azimuth_rad,
            };
        }
        // (cos, sin) of every source angle, computed once.
        let unit = |field: &[f32]| -> Vec<(f32, f32)> {
            field[..h * w].iter().map(|a| (a.cos(), a.sin())).collect()
        };
        let (elevation_unit, azimuth_unit) = (unit(&self.elevation_rad), unit(&self.azimuth_rad));
        for i in 0..height {
            let u = source_coord(i, height, h);
            // Two rows that bracket u (or the two outermost ones), t relative to r0.
            let r0 = if h == 1 {
                0
            } else {
                (u.floor().max(0.0) as usize).min(h - 2)
            };
            let r1 = (r0 + 1).min(h - 1);
            let t = if r1 == r0 { 0.0 } else { u - r0 as f32 };
            for j in 0..width {
                let v = source_coord(j, width, w).rem_euclid(w as f32);
                let c0 = (v.floor() as usize).min(w - 1);
                let c1 = (c0 + 1) % w;
                let s = v - c0 as f32;
                let at = |field: &[(f32, f32)]| {
                    [
                        field[r0 * w + c0],
                        field[r0 * w + c1],
                        field[r1 * w + c0],
                        field[r1 * w + c1],
                    ]
                };
                elevation_rad.push(lerp_angle(at(&elevation_unit), t, s));
                azimuth_rad.push(lerp_angle(at(&azimuth_unit), t, s));
            }
        }
        AngleGrid {
            height,
            width,
            elevation_rad,
            azimuth_rad,
        }
    }

    /// Circular mean elevation of each row (exact for the separable grids that
    /// profiles and [`AngleGrid::resized`] produce).
    pub fn row_elevations(&self) -> Vec<f32> {
        (0..self.height)
            .map(|i| circular_mean((0..self.width).map(|j| self.elevation_rad[i * self.width + j])))
            .collect()
    }

    /// Circular mean azimuth of each column.
    pub fn column_azimuths(&self) -> Vec<f32> {
        (0..self.width)
            .map(|j| circular_mean((0..self.height).map(|i| self.azimuth_rad[i * self.width + j])))
            .collect()
    }
}

impl SensorProfile {
    /// The same sensor resampled to `beams x columns`: the elevation table is
    /// interpolated like [`AngleGrid::resized`] (so `profile.resampled(h, w).angle_grid()`
    /// equals `profile.angle_grid().resized(h, w)`), range limits are kept. Per-beam
    /// azimuth offsets are dropped, as resampled beams are not physical lasers.
    pub fn resampled(&self, beams: usize, columns: usize) -> SensorProfile {
        let grid =
            AngleGrid::regular_columns(self.beams(), 1, |i| self.elevation_deg[i].to_radians());
        let rows = grid.resized(beams, 1).row_elevations();
        SensorProfile {
            name: format!("{}@{}x{}", self.name, beams, columns),
            elevation_deg: rows.iter().map(|e| e.to_degrees()).collect(),
            azimuth_offset_deg: None,
            columns,
            min_range_m: self.min_range_m,
            max_range_m: self.max_range_m,
        }
    }
}

fn circular_mean(angles: impl Iterator<Item = f32>) -> f32 {
    let (mut c, mut s) = (0.0f64, 0.0f64);
    for a in angles {
        c += f64::from(a.cos());
        s += f64::from(a.sin());
    }
    s.atan2(c) as f32
}
