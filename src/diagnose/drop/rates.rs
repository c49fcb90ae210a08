//! The free-rate families: `beam_dropout` (a rate per laser), `edge_dropout` (rates
//! beside depth edges per range band) and `material_dropout` (a rate per class).

use serde_json::{Map, Value, json};

use super::round3;
use crate::diagnose::fit::{DropFamily, DropFit, Pixels, QTable};
use crate::lidar::edges::MAX_EDGE_PX;
use crate::physics::dropout::EdgeBand;
use crate::sim::material::label;

/// The drop probability that, on top of a `reference` drop rate, gives `rate` (0 where
/// `rate` is below it): independent drops compose as 1 - (1 - p)(1 - reference).
fn excess_drop(rate: f64, reference: f64) -> f64 {
    ((rate - reference) / (1.0 - reference).max(1e-6)).max(0.0)
}

/// Rows (or classes) by fitted rate, strongest first, as words.
fn strongest(items: &[(String, f64)], n: usize) -> String {
    let mut v: Vec<&(String, f64)> = items.iter().filter(|x| x.1 > 0.005).collect();
    v.sort_by(|a, b| b.1.total_cmp(&a.1));
    v.iter()
        .take(n)
        .map(|(name, p)| format!("{name} ({:.0} %)", 100.0 * p))
        .collect::<Vec<_>>()
        .join(", ")
}

/// `beam_dropout`: one free drop rate per row (laser).
/// A dropped pixel counts for a laser's rate when returns enclose it within
/// this many pixels (`Pixels::laser_px`: one surface, or the ground above the bottom row).
const BEAM_ENCLOSURE_PX: u8 = 3;
/// ... and for a class's rate within this many.
const CLASS_ENCLOSURE_PX: u8 = 8;

pub struct BeamFamily;

/// A weak laser is weak all round: its rate is fitted in each quarter turn of
/// columns, and the excess it keeps is the one that at least half of the
/// quarters reach. Holes that one part of the scene makes in a band of rows
/// (gaps between tree crowns near the horizon) are not in every quarter, and a
/// quarter of open field has no surface to show a laser's weakness at all.
const BEAM_SIDES: usize = 4;
/// How many quarters must reach a laser's excess drop rate.
const BEAM_SIDES_WEAK: usize = 2;

impl DropFamily for BeamFamily {
    fn id(&self) -> &'static str {
        "beam_dropout"
    }
    fn bins(&self, px: &Pixels) -> usize {
        px.height * BEAM_SIDES
    }
    /// Pixels with a surface only: a laser's sensitivity shows on what it can
    /// hit; how much open space a row sees is the scene's.
    fn bin(&self, px: &Pixels, i: usize) -> Option<usize> {
        let side = (px.column[i] as usize * BEAM_SIDES / px.width.max(1)).min(BEAM_SIDES - 1);
        // The last tenth of the reach is where surfaces pass out of range: a
        // hole there is range's, not a laser's.
        (px.laser_px[i] <= BEAM_ENCLOSURE_PX && px.range_m[i] <= 0.9 * px.reach_m)
            .then_some(px.row[i] as usize * BEAM_SIDES + side)
    }
    fn fit(&self, table: &QTable, _: &Pixels) -> Option<DropFit> {
        if table.bins == 0 {
            return None;
        }
        let rows = table.bins / BEAM_SIDES;
        // Per-laser differences, not a smooth trend over rows: a trend is what
        // range, incidence or sky change, and a constant is the keep scale. The
        // rate above the running median of its 7 neighbouring rows (in the same
        // quarter) is the beam's.
        let free: Vec<f64> = (0..table.bins).map(|b| table.best_bin_prob(b)).collect();
        let excess = |r: usize, side: usize| {
            let mut window: Vec<f64> = (r.saturating_sub(3)..(r + 4).min(rows))
                .map(|q| free[q * BEAM_SIDES + side])
                .collect();
            window.sort_by(f64::total_cmp);
            excess_drop(free[r * BEAM_SIDES + side], window[window.len() / 2])
        };
        let per_row: Vec<f64> = (0..rows)
            .map(|r| {
                let mut e: Vec<f64> = (0..BEAM_SIDES).map(|side| excess(r, side)).collect();
                e.sort_by(|a, b| b.total_cmp(a));
                e[BEAM_SIDES_WEAK - 1]
            })
            .collect();
        let drop_prob: Vec<f64> = (0..table.bins).map(|b| per_row[b / BEAM_SIDES]).collect();
        let rates: Vec<f64> = per_row.iter().map(|p| round3(*p)).collect();
        let items: Vec<(String, f64)> = per_row
            .iter()
            .enumerate()
            .map(|(r, p)| (format!("row {r}"), *p))
            .collect();
        let mut params = Map::new();
        params.insert("rates".into(), json!(rates));
        let mut physics = Map::new();
        physics.insert("beam_dropout".into(), json!({ "rates": rates }));
        Some(DropFit {
            n_params: rates.len(),
            drop_prob,
            params,
            physics,
            location: format!("per-laser rates; weakest rows: {}", strongest(&items, 6)),
        })
    }
}

/// `edge_dropout`: extra drops on and beside depth edges, per range band of the pixel.
pub struct EdgeFamily;
/// Distances from an edge (0 = on it) that get a rate of their own; beyond them the rate of
/// the pixels far from any edge is the reference.
const EDGE_FIT_PX: usize = 4;
/// Lower ends of the range bands that get edge rates of their own: how much of a beam an
/// edge takes (and the emitter-receiver parallax behind a near edge) changes with range.
const EDGE_BANDS_M: [f32; 4] = [0.0, 10.0, 20.0, 40.0];
const EDGE_DISTANCES: usize = MAX_EDGE_PX as usize + 1;

fn edge_band(range_m: f32) -> usize {
    EDGE_BANDS_M
        .iter()
        .rposition(|&from| range_m >= from)
        .unwrap_or(0)
}

/// One band's drop rates 0 .. [`EDGE_FIT_PX`] pixels from an edge: what the rest of the
/// model leaves unexplained there, above what it leaves in the band's pixels far from any
/// edge (that is the keep scale's). Distances without pixels get 0.
fn edge_band_rates(table: &QTable, band: usize) -> Vec<f64> {
    let bins = band * EDGE_DISTANCES..(band + 1) * EDGE_DISTANCES;
    let free: Vec<f64> = bins.clone().map(|b| table.best_bin_prob(b)).collect();
    let pixels: Vec<f64> = bins
        .map(|b| {
            let (kept, dropped) = table.counts(b);
            kept + dropped
        })
        .collect();
    let far_pixels: f64 = pixels[EDGE_FIT_PX..].iter().sum();
    let far = if far_pixels > 0.0 {
        let dropped: f64 = free[EDGE_FIT_PX..]
            .iter()
            .zip(&pixels[EDGE_FIT_PX..])
            .map(|(p, n)| p * n)
            .sum();
        dropped / far_pixels
    } else {
        0.0
    };
    (0..EDGE_FIT_PX)
        .map(|d| {
            if pixels[d] > 0.0 {
                round3(excess_drop(free[d], far))
            } else {
                0.0
            }
        })
        .collect()
}

impl DropFamily for EdgeFamily {
    fn id(&self) -> &'static str {
        "edge_dropout"
    }
    fn bins(&self, _: &Pixels) -> usize {
        EDGE_BANDS_M.len() * EDGE_DISTANCES
    }
    /// Pixels with a surface only (a completed range): edges are between surfaces.
    /// Enclosed by any returns, not by one surface: a ray dropped on a depth edge
    /// has the edge's two surfaces beside it.
    fn bin(&self, px: &Pixels, i: usize) -> Option<usize> {
        let r = px.range_m[i];
        (r.is_finite() && px.enclosure_px[i] <= BEAM_ENCLOSURE_PX).then(|| {
            edge_band(r) * EDGE_DISTANCES + usize::from(px.row_edge_px[i].min(MAX_EDGE_PX))
        })
    }
    fn fit(&self, table: &QTable, _: &Pixels) -> Option<DropFit> {
        if table.bins != EDGE_BANDS_M.len() * EDGE_DISTANCES {
            return None;
        }
        let by_band: Vec<Vec<f64>> = (0..EDGE_BANDS_M.len())
            .map(|band| edge_band_rates(table, band))
            .collect();
        let mut drop_prob = vec![0.0; table.bins];
        for (band, rates) in by_band.iter().enumerate() {
            drop_prob[band * EDGE_DISTANCES..][..EDGE_FIT_PX].copy_from_slice(rates);
        }
        // The simulator's own type, so `render --physics` reads back what is written here.
        let bands: Vec<EdgeBand> = EDGE_BANDS_M
            .iter()
            .zip(&by_band)
            .map(|(&from_m, rates)| EdgeBand {
                from_m,
                drop_prob_by_px: rates.iter().map(|&r| r as f32).collect(),
            })
            .collect();
        let mut params = Map::new();
        params.insert("bands".into(), json!(bands));
        let mut physics = Map::new();
        physics.insert("edge_dropout".into(), json!({ "bands": bands }));
        let on_edge: Vec<String> = by_band.iter().map(|r| format!("{:.2}", r[0])).collect();
        let ranges: Vec<String> = EDGE_BANDS_M
            .iter()
            .enumerate()
            .map(|(b, from)| match EDGE_BANDS_M.get(b + 1) {
                Some(to) => format!("{from:.0}-{to:.0}"),
                None => format!("{from:.0}+"),
            })
            .collect();
        Some(DropFit {
            n_params: EDGE_FIT_PX * EDGE_BANDS_M.len(),
            drop_prob,
            params,
            physics,
            location: format!(
                "depth edges: {} of the rays on an edge drop at {} m",
                on_edge.join(" / "),
                ranges.join(" / ")
            ),
        })
    }
}

/// `material_dropout`: one free drop rate per semantic class (real data has
/// classes, not materials; see docs/diagnose.md).
pub struct ClassFamily;
const CLASSES: usize = 260;
/// A class needs this many training pixels to get a rate of its own.
const MIN_CLASS_PIXELS: f64 = 200.0;
/// Smallest extra drop rate of a class that is attributed to its material.
const MIN_CLASS_PROB: f64 = 0.08;

impl DropFamily for ClassFamily {
    /// A class is a proxy for materials whose mix differs object by object
    /// (paint colours, window shares), so its rate need not be the same ahead
    /// and behind.
    fn azimuth_invariant(&self) -> bool {
        false
    }
    fn id(&self) -> &'static str {
        "material_dropout"
    }
    fn bins(&self, _: &Pixels) -> usize {
        CLASSES
    }
    /// Enclosed pixels only: a dropped pixel at an object's outline takes the
    /// object's class from its neighbours, and how much outline borders open
    /// space is the scene's. Wider than the beam's: a window dropped at high
    /// rates leaves big holes that are still the object's.
    fn bin(&self, px: &Pixels, i: usize) -> Option<usize> {
        let c = px.class[i] as usize;
        (px.enclosure_px[i] <= CLASS_ENCLOSURE_PX && c != 0 && c < CLASSES).then_some(c)
    }
    fn fit(&self, table: &QTable, _: &Pixels) -> Option<DropFit> {
        let mut drop_prob = vec![0.0; table.bins];
        let mut by_class = Map::new();
        let mut items = Vec::new();
        let mut n_params = 0;
        for (b, p) in drop_prob.iter_mut().enumerate() {
            let (kept, dropped) = table.counts(b);
            if kept + dropped < MIN_CLASS_PIXELS {
                continue;
            }
            n_params += 1;
            // Small class differences are what scenes differ by (materials per
            // class vary: car paints, window shares); only marked ones count.
            *p = table.best_bin_prob(b);
            if *p < MIN_CLASS_PROB {
                *p = 0.0;
            }
            if *p > 0.005 {
                by_class.insert(b.to_string(), json!(round3(*p)));
                items.push((format!("{} ({b})", label::name(b as u32)), *p));
            }
        }
        if n_params == 0 {
            return None;
        }
        let mut params = Map::new();
        params.insert("drop_prob_by_class".into(), Value::Object(by_class.clone()));
        let mut physics = Map::new();
        physics.insert(
            "material_dropout".into(),
            json!({ "drop_prob_by_class": by_class }),
        );
        Some(DropFit {
            drop_prob,
            params,
            physics,
            n_params,
            location: format!("classes {}", strongest(&items, 5)),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::diagnose::fit::ENCLOSURE_CAP_PX;

    /// Eight rows of 400 columns of a wall 10 m away; `weak(row, column)` pixels
    /// keep 7 rays in 10, the others 19 in 20.
    fn wall_rows(weak: impl Fn(usize, usize) -> bool) -> Pixels {
        let (h, w) = (8, 400);
        let mut px = Pixels {
            height: h,
            width: w,
            reach_m: 100.0,
            ..Default::default()
        };
        for i in 0..h {
            for j in 0..w {
                px.row.push(i as u16);
                px.column.push(j as u16);
                px.range_m.push(10.0);
                px.enclosure_px.push(1);
                px.surface_px.push(1);
                px.laser_px.push(1);
                px.kept
                    .push(if weak(i, j) { j % 10 >= 3 } else { j % 20 != 0 });
            }
        }
        px
    }

    fn beam_rates(px: &Pixels) -> Vec<f64> {
        let table = QTable::build(&BeamFamily, px, &vec![0.95; px.len()]);
        let fit = BeamFamily.fit(&table, px).unwrap();
        (0..px.height)
            .map(|r| fit.drop_prob[r * BEAM_SIDES])
            .collect()
    }

    #[test]
    fn a_weak_laser_is_weak_all_round() {
        let all_round = beam_rates(&wall_rows(|i, _| i == 4));
        assert!(
            (all_round[4] - (1.0 - 0.7 / 0.95)).abs() < 0.01,
            "{all_round:?}"
        );
        assert!(
            all_round
                .iter()
                .enumerate()
                .all(|(r, p)| r == 4 || *p < 1e-3)
        );
        // The same holes in one quarter turn only are the scene's.
        let one_quarter = beam_rates(&wall_rows(|i, j| i == 4 && j < 100));
        assert!(one_quarter.iter().all(|p| *p < 1e-3), "{one_quarter:?}");
    }

    #[test]
    fn a_ray_dropped_on_a_depth_edge_counts_for_edges_not_for_lasers() {
        // Returns on both sides, 1 px away, on the two surfaces of the edge.
        let px = Pixels {
            height: 1,
            width: 1,
            reach_m: 100.0,
            row: vec![0],
            column: vec![0],
            range_m: vec![20.0],
            kept: vec![false],
            enclosure_px: vec![1],
            surface_px: vec![ENCLOSURE_CAP_PX],
            laser_px: vec![ENCLOSURE_CAP_PX],
            row_edge_px: vec![0],
            ..Default::default()
        };
        assert!(EdgeFamily.bin(&px, 0).is_some());
        assert_eq!(BeamFamily.bin(&px, 0), None);
    }
}
