//! The `motion_distortion` family as the drop mask sees it: pixels that a sensor's
//! motion during the sweep leaves without a landed return.

use std::collections::HashMap;
use std::hash::{DefaultHasher, Hash, Hasher};
use std::sync::{Arc, Mutex};

use rayon::prelude::*;
use serde_json::{Map, json};

use super::{fit_curve, round3};
use crate::diagnose::fit::{DropFamily, DropFit, Pixels, QTable};

/// `motion_distortion` as the drop mask sees it. A sensor that moves by `m` during
/// the sweep moves each return by `−m · t(φ)/T` along its heading: horizontal
/// range by `Δρ = −m · t/T · cos φ`, azimuth by `Δφ = m · t/T · sin φ / ρ`, and
/// elevation by `Δe = −sin(e) · Δρ / r`. A pixel stays filled while some return lands
/// within half a pixel of it. Columns always come from azimuth, so they spread
/// apart where returns are near (ahead and behind). Where rows come from elevation
/// (clouds without beam numbers), rows empty at the edges (the bottom rows behind
/// a car moving forward, the top rows ahead) and between ground rows ahead, which
/// spread apart because nearer (lower) rows move more (`Δe ≈ sin²|e| · m / h` on flat
/// ground). Built only when the seam's range step found motion; the motion per
/// sweep is chosen by fit at the scale of the seam's step. A pixel's feature is its
/// distance to the nearest landed return along its column and along its row, and a
/// two-parameter curve in each (either may be off) fits how much is lost: how many
/// returns a sensor fires per column is not in the data. The sweep starts at the seam
/// the clouds' firing order shows (else straight ahead); its direction, where the order
/// does not say, and where rows come from are chosen by fit too.
pub struct MotionCoverageFamily {
    /// How far the sensor moves during one sweep.
    pub motion_per_sweep_m: f32,
    /// Azimuth where the sweep starts, radians.
    pub sweep_start_rad: f32,
    /// Whether the sweep turns towards positive azimuth.
    pub counter_clockwise: bool,
    /// Whether rows come from elevation (and so move with it), not beam numbers.
    pub rows_from_elevation: bool,
    /// Bins already computed, by a fingerprint of the pixel set's content: the
    /// selection asks for the same sets' bins in every round.
    /// (`u16::MAX`: no bin)
    bins_by_set: Mutex<HashMap<u64, Arc<Vec<u16>>>>,
}
/// Distance bins per axis: a quarter of half a pixel each, the last open-ended.
const GAP_BIN: f32 = 0.25;
const GAP_BINS: usize = 16;

impl MotionCoverageFamily {
    pub fn new(
        motion_per_sweep_m: f32,
        sweep_start_rad: f32,
        counter_clockwise: bool,
        rows_from_elevation: bool,
    ) -> Self {
        Self {
            motion_per_sweep_m,
            sweep_start_rad,
            counter_clockwise,
            rows_from_elevation,
            bins_by_set: Mutex::default(),
        }
    }

    fn compute_bins(&self, px: &Pixels) -> Vec<u16> {
        let gaps: Vec<Vec<[f32; 2]>> = (0..px.scan_range_m.len())
            .into_par_iter()
            .map(|scan| self.scan_gaps(px, scan))
            .collect();
        (0..px.len())
            .map(|i| gap_bin(gaps.get(*px.scan.get(i)? as usize)?[in_scan(px, i)]))
            .map(|b| b.map_or(u16::MAX, |b| b as u16))
            .collect()
    }

    /// For every pixel of one scan (row-major), the distance in half pixels from its
    /// centre to the nearest landed return along its column and along its row (NaN
    /// where none lands in that column or row at all).
    fn scan_gaps(&self, px: &Pixels, scan: usize) -> Vec<[f32; 2]> {
        let (h, w) = (px.height, px.width);
        let mut gaps = vec![[f32::NAN; 2]; h * w];
        let Some(ranges) = px.scan_range_m.get(scan) else {
            return gaps;
        };
        let (elevation, azimuth) = (&px.row_elevation_rad, &px.column_azimuth_rad);
        if h < 2 || w < 2 || elevation.len() != h || azimuth.len() != w || ranges.len() != h * w {
            return gaps;
        }
        let column_step = std::f32::consts::TAU / w as f32;
        // Per column: how far the sensor has moved when it fires there, and the
        // heading's components along the ray and across it.
        let columns: Vec<(f32, f32, f32)> = azimuth
            .iter()
            .map(|&phi| {
                let turned = if self.counter_clockwise {
                    phi - self.sweep_start_rad
                } else {
                    self.sweep_start_rad - phi
                };
                let moved = self.motion_per_sweep_m * turned.rem_euclid(std::f32::consts::TAU)
                    / std::f32::consts::TAU;
                (moved, phi.cos(), phi.sin())
            })
            .collect();
        let mut rows_at: Vec<Vec<f32>> = vec![Vec::new(); w];
        let mut columns_at: Vec<Vec<f32>> = vec![Vec::new(); h];
        for (k, &e) in elevation.iter().enumerate() {
            let (sin_e, cos_e) = e.sin_cos();
            for (c, &(moved, cos_phi, sin_phi)) in columns.iter().enumerate() {
                let r = ranges[k * w + c];
                if !(r.is_finite() && r > 0.1) {
                    continue;
                }
                if self.rows_from_elevation {
                    rows_at[c].push(row_position(px, e + sin_e * moved * cos_phi / r));
                }
                // Columns run from azimuth +180 deg down to -180 deg.
                let d_phi = moved * sin_phi / (r * cos_e).max(0.1);
                columns_at[k].push((c as f32 - d_phi / column_step).rem_euclid(w as f32));
            }
        }
        for v in rows_at.iter_mut().chain(columns_at.iter_mut()) {
            v.sort_by(f32::total_cmp);
        }
        for k in 0..h {
            for c in 0..w {
                let along_column = if self.rows_from_elevation {
                    nearest(&rows_at[c], k as f32, None)
                } else {
                    0.0
                };
                let along_row = nearest(&columns_at[k], c as f32, Some(w as f32));
                gaps[k * w + c] = [2.0 * along_column, 2.0 * along_row];
            }
        }
        gaps
    }

    /// The direction in words.
    fn sweep(&self) -> &'static str {
        if self.counter_clockwise {
            "counter-clockwise"
        } else {
            "clockwise"
        }
    }
}

/// Pixel `i`'s index in its scan's row-major image.
fn in_scan(px: &Pixels, i: usize) -> usize {
    px.row[i] as usize * px.width + px.column[i] as usize
}

/// A hash of everything a pixel set's coverage bins depend on.
fn fingerprint(px: &Pixels) -> u64 {
    let mut h = DefaultHasher::new();
    (px.height, px.width, &px.row, &px.column, &px.scan).hash(&mut h);
    for v in [&px.row_elevation_rad, &px.column_azimuth_rad]
        .into_iter()
        .chain(&px.scan_range_m)
    {
        v.len().hash(&mut h);
        v.iter().for_each(|x| x.to_bits().hash(&mut h));
    }
    h.finish()
}

/// Distance from `y` to the nearest of the sorted `landed` (on a circle of
/// `period` if given); NaN when nothing landed.
fn nearest(landed: &[f32], y: f32, period: Option<f32>) -> f32 {
    let (Some(&first), Some(&last)) = (landed.first(), landed.last()) else {
        return f32::NAN;
    };
    let above = landed.partition_point(|&l| l < y);
    let mut near = [above.checked_sub(1), Some(above)]
        .into_iter()
        .flatten()
        .filter_map(|j| landed.get(j))
        .map(|l| (l - y).abs())
        .fold(f32::INFINITY, f32::min);
    if let Some(p) = period {
        near = near.min((first + p - y).abs()).min((y + p - last).abs());
    }
    near
}

/// Fractional row index of elevation `e` on the grid's rows (top row first),
/// extended beyond the edges with the edge rows' spacing.
fn row_position(px: &Pixels, e: f32) -> f32 {
    let el = &px.row_elevation_rad;
    let h = el.len();
    let step = |a: usize, b: usize| {
        let d = el[a] - el[b];
        if d.abs() > 1e-6 { d } else { 1e-6 }
    };
    // Rows run from the highest elevation down.
    let below = el.partition_point(|&x| x > e);
    let (a, b) = match below {
        0 => (0, 1),
        k if k >= h => (h - 2, h - 1),
        k => (k - 1, k),
    };
    a as f32 + (el[a] - e) / step(a, b)
}

/// The (along-column, along-row) bin of a pixel's gaps, flattened.
fn gap_bin([along_column, along_row]: [f32; 2]) -> Option<usize> {
    let axis = |g: f32| {
        g.is_finite()
            .then(|| ((g / GAP_BIN) as usize).min(GAP_BINS - 1))
    };
    Some(axis(along_column)? * GAP_BINS + axis(along_row)?)
}

/// One axis's logistic curve over the gap bins (`a` infinite: off).
fn gap_curve(a: f32, b: f32) -> Vec<f64> {
    (0..GAP_BINS)
        .map(|bin| {
            let x = (bin as f32 + 0.5) * GAP_BIN;
            if a.is_finite() {
                1.0 / (1.0 + f64::from((a - x) / b).exp())
            } else {
                0.0
            }
        })
        .collect()
}

/// Drop probability per flattened bin: either axis's curve may empty a pixel.
fn gap_probs(column: &[f64], row: &[f64]) -> Vec<f64> {
    column
        .iter()
        .flat_map(|pc| row.iter().map(move |pr| 1.0 - (1.0 - pc) * (1.0 - pr)))
        .collect()
}

impl DropFamily for MotionCoverageFamily {
    fn azimuth_invariant(&self) -> bool {
        false
    }
    fn established(&self) -> bool {
        true
    }
    fn id(&self) -> &'static str {
        "motion_distortion"
    }
    fn bins(&self, _: &Pixels) -> usize {
        GAP_BINS * GAP_BINS
    }
    fn bin(&self, px: &Pixels, i: usize) -> Option<usize> {
        gap_bin(self.scan_gaps(px, *px.scan.get(i)? as usize)[in_scan(px, i)])
    }
    fn bins_of(&self, px: &Pixels) -> Vec<Option<usize>> {
        let key = fingerprint(px);
        let cached = self
            .bins_by_set
            .lock()
            .ok()
            .and_then(|m| m.get(&key).cloned());
        let bins = cached.unwrap_or_else(|| {
            let bins = Arc::new(self.compute_bins(px));
            if let Ok(mut m) = self.bins_by_set.lock() {
                m.insert(key, bins.clone());
            }
            bins
        });
        bins.iter()
            .map(|&b| (b != u16::MAX).then_some(usize::from(b)))
            .collect()
    }
    /// The two curves by coordinate descent, each over its grid given the other.
    fn fit(&self, table: &QTable, _: &Pixels) -> Option<DropFit> {
        if table.bins != GAP_BINS * GAP_BINS {
            return None;
        }
        let grid_a: Vec<f32> = std::iter::once(f32::INFINITY)
            .chain((0..=30).map(|i| 0.25 + 0.1 * i as f32))
            .collect();
        let grid_b = [0.05, 0.1, 0.2, 0.3, 0.5, 0.8];
        // (a, b) along columns, then along rows.
        let mut curves = [(f32::INFINITY, 1.0f32); 2];
        for _ in 0..3 {
            for axis in [1, 0] {
                if axis == 0 && !self.rows_from_elevation {
                    continue;
                }
                let other = curves[1 - axis];
                let other_probs = gap_curve(other.0, other.1);
                let (a, b, _) = fit_curve(table, &grid_a, &grid_b, |a, b| {
                    let this = gap_curve(a, b);
                    if axis == 0 {
                        gap_probs(&this, &other_probs)
                    } else {
                        gap_probs(&other_probs, &this)
                    }
                })?;
                curves[axis] = (a, b);
            }
        }
        let [column, row] = curves;
        let drop_prob = gap_probs(&gap_curve(column.0, column.1), &gap_curve(row.0, row.1));
        let mut params = Map::new();
        let mut words = Vec::new();
        for ((a, b), axis, what) in [
            (
                column,
                "rows",
                "rows at the edges and between the ground rows ahead (rows come from elevation)",
            ),
            (row, "columns", "columns spread apart near the sensor"),
        ] {
            if a.is_finite() {
                params.insert(
                    format!("{axis}_shift_50_half_pixels"),
                    json!(round3(a.into())),
                );
                params.insert(format!("{axis}_width_half_pixels"), json!(round3(b.into())));
                words.push(format!("{what}, beyond {a:.1} half pixels"));
            }
        }
        params.insert(
            "motion_per_sweep_m".into(),
            json!(round3(self.motion_per_sweep_m.into())),
        );
        Some(DropFit {
            drop_prob,
            params,
            physics: Map::new(),
            // Two per curve in use, and the motion per sweep, chosen by fit too.
            n_params: 1 + 2 * words.len(),
            location: format!(
                "pixels empty where the sweep ({} from {:.0} deg, {:.2} m per sweep) moves every return away from them: {}",
                self.sweep(),
                self.sweep_start_rad.to_degrees(),
                self.motion_per_sweep_m,
                if words.is_empty() {
                    "nowhere".to_string()
                } else {
                    words.join("; ")
                }
            ),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::Value;

    /// One scan of ground rows (1 deg apart from -10 deg down) 1.5 m up, 360
    /// columns; pixels dropped where `dropped([along column, along row])` says.
    fn ground(
        rows: usize,
        dropped: impl Fn([f32; 2]) -> bool,
        motion: &MotionCoverageFamily,
    ) -> Pixels {
        let (h, w) = (rows, 360usize);
        let mut px = Pixels {
            height: h,
            width: w,
            row_elevation_rad: (0..h).map(|i| (-10.0 - i as f32).to_radians()).collect(),
            column_azimuth_rad: (0..w)
                .map(|j| (180.0 - (j as f32 + 0.5)).to_radians())
                .collect(),
            ..Default::default()
        };
        let mut ranges = Vec::new();
        for row in 0..h {
            for j in 0..w {
                px.row.push(row as u16);
                px.column.push(j as u16);
                let r = 1.5 / px.row_elevation_rad[row].abs().sin();
                px.range_m.push(r);
                ranges.push(r);
                px.cos_incidence.push(0.5);
                px.class.push(0);
                px.enclosure_px.push(0);
                px.surface_px.push(0);
                px.laser_px.push(0);
                px.kept.push(true);
                px.scan.push(0);
            }
        }
        px.scan_range_m.push(ranges);
        let gaps = motion.scan_gaps(&px, 0);
        for (kept, gap) in px.kept.iter_mut().zip(gaps) {
            *kept = !dropped(gap);
        }
        px
    }

    fn gap_at(motion: &MotionCoverageFamily, px: &Pixels, row: usize, az_deg: f32) -> [f32; 2] {
        motion.scan_gaps(px, 0)[row * px.width + (180.0 - az_deg) as usize]
    }

    fn fitted(motion: &MotionCoverageFamily, px: &Pixels, key: &str) -> Option<f64> {
        let table = QTable::build(motion, px, &vec![1.0; px.len()]);
        let fit = motion.fit(&table, px).unwrap();
        fit.params.get(key).and_then(Value::as_f64)
    }

    #[test]
    fn motion_empties_the_rows_no_beam_lands_in_and_the_fit_finds_where() {
        let motion = MotionCoverageFamily::new(0.8, 0.0, true, true);
        let px = ground(8, |[rows, _]| rows > 1.0, &motion);
        // Straight behind, half a sweep in: returns 0.4 m farther, lifted by
        // sin(17 deg) * 0.4 m / r; the bottom row's nearest returns are its own.
        let r = 1.5 / 17f32.to_radians().sin();
        let lift = 17f32.to_radians().sin() * 0.4 / r / 1f32.to_radians();
        let behind = gap_at(&motion, &px, 7, 179.5)[0];
        assert!(
            (behind - 2.0 * lift).abs() < 0.05,
            "{behind} vs {}",
            2.0 * lift
        );
        // Ahead, late in the sweep, returns come nearer and move down, lower rows
        // more: the top row has nothing above to refill it, and the rows spread.
        assert!(gap_at(&motion, &px, 0, -30.5)[0] > 0.0);
        assert!(gap_at(&motion, &px, 7, -30.5)[0] < gap_at(&motion, &px, 0, -30.5)[0]);
        // Early in the sweep nothing has moved yet.
        assert!((0..8).all(|row| gap_at(&motion, &px, row, 2.5)[0] < 0.05));
        // The bin and the per-pixel bin agree, and the kept bins belong to their set.
        let i = px.len() - 1;
        assert_eq!(motion.bin(&px, i), motion.bins_of(&px)[i]);
        let other = ground(6, |_| false, &motion);
        let fresh = MotionCoverageFamily::new(0.8, 0.0, true, true);
        assert_eq!(motion.bins_of(&other), fresh.bins_of(&other));
        assert_eq!(motion.bins_of(&px), fresh.bins_of(&px));
        let at = fitted(&motion, &px, "rows_shift_50_half_pixels").unwrap();
        assert!((0.8..=1.3).contains(&at), "shift_50 {at}");
        let dropped = px.kept.iter().filter(|k| !**k).count();
        assert!((20..1500).contains(&dropped), "{dropped} dropped");
    }

    #[test]
    fn without_motion_every_pixel_is_covered() {
        let still = MotionCoverageFamily::new(0.0, 0.0, false, true);
        let px = ground(8, |_| false, &still);
        assert!(still.bins_of(&px).iter().all(|b| *b == Some(0)));
    }

    #[test]
    fn with_beam_numbers_only_the_columns_spread() {
        let motion = MotionCoverageFamily::new(1.5, 0.0, true, false);
        let px = ground(8, |[_, columns]| columns > 1.0, &motion);
        let gaps = motion.scan_gaps(&px, 0);
        let row = |k: usize| -> Vec<f32> {
            gaps[k * px.width..(k + 1) * px.width]
                .iter()
                .map(|g| g[1])
                .collect()
        };
        // Bottom row (4.9 m away), late in the sweep ahead: returns move sideways by up
        // to ~1.5 m · sin φ / ρ, and the columns there spread by ~1.5 m / ρ (30 %), so
        // some pixels have no return within half a column.
        assert!(row(7)[180..215].iter().any(|g| *g > 1.2), "{:?}", row(7));
        // Sideways (azimuth 90 deg) only the sweep's progress spreads them (~5 %), and
        // rows never move.
        assert!(
            row(7)[88..92].iter().all(|g| *g < 1.2),
            "{:?}",
            &row(7)[88..92]
        );
        assert!(gaps.iter().all(|g| g[0] == 0.0));
        let at = fitted(&motion, &px, "columns_shift_50_half_pixels").unwrap();
        assert!((0.8..=1.3).contains(&at), "shift_50 {at}");
        assert_eq!(fitted(&motion, &px, "rows_shift_50_half_pixels"), None);
    }

    #[test]
    fn row_positions_interpolate_and_extend_past_the_edges() {
        let px = Pixels {
            row_elevation_rad: vec![0.02, 0.0, -0.02],
            ..Default::default()
        };
        assert!((row_position(&px, 0.01) - 0.5).abs() < 1e-4);
        assert!((row_position(&px, -0.03) - 2.5).abs() < 1e-4);
        assert!((row_position(&px, 0.04) + 1.0).abs() < 1e-4);
    }
}
