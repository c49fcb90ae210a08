//! The baseline `B(x)`: the simulated recording's own keep rate per pixel cell (times an
//! azimuth factor for the sim's own blind spots), which holds what sim and real share.

use super::Pixels;

/// Width of the baseline's range cells, meters.
const BASELINE_RANGE_BIN_M: f32 = 2.0;
/// Prior weight (pixels) of the coarser rate in each baseline cell.
const SMOOTHING_PIXELS: f64 = 20.0;

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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::diagnose::fit::ENCLOSURE_CAP_PX;

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
}
