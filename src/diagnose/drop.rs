//! The candidate drop models of the diagnosis, one [`DropFamily`] each: what
//! feature bin a pixel falls in and how the per-bin drop probabilities are fitted
//! by maximum likelihood (see `fit` for the model and the selection).
//!
//! | family | feature | model |
//! |---|---|---|
//! | `range_dropout` | completed range (drops only where returns enclose them), 1 m bins | the physics module's log-logistic curve (range_50_m, softness) |
//! | `incidence_dropout` | cos(incidence) of the completed normal, 0.02 bins | log-logistic in cos (cos_50, softness) |
//! | `beam_dropout` | row | one free rate per row |
//! | `material_dropout` | semantic class (labels, else neighbours' labels) | one free rate per class |
//! | `edge_dropout` | pixels along the row to the nearest depth edge of the completed range, 0-8 | a free rate for 0-3 px above the rate far from edges |
//! | `self_occlusion` | (row, azimuth sector) in the lower half | per sector a "skyline" of blocked bottom rows and a probability |
//! | `motion_distortion` (coverage) | distance to the nearest moved return along the pixel's column and along its row, in half pixels | a logistic curve per axis; only where the seam step found motion |

use std::collections::HashMap;
use std::hash::{DefaultHasher, Hash, Hasher};
use std::sync::{Arc, Mutex};

use rayon::prelude::*;
use serde_json::{Map, Value, json};

use super::fit::{DropFamily, DropFit, Pixels, QTable, golden};
use crate::lidar::edges::MAX_EDGE_PX;
use crate::physics::dropout::{EdgeBand, IncidenceDropout, RangeDropout};
use crate::physics::{Effect, RayFeatures};
use crate::sim::Material;
use crate::sim::material::label;

/// All drop candidates.
pub fn families() -> Vec<Box<dyn DropFamily>> {
    vec![
        Box::new(RangeFamily),
        Box::new(IncidenceFamily),
        Box::new(BeamFamily),
        Box::new(ClassFamily),
        Box::new(SelfOcclusionFamily),
        Box::new(EdgeFamily),
    ]
}

fn ray(range_m: f32, incidence_rad: f32) -> RayFeatures {
    RayFeatures {
        row: 0,
        column: 0,
        range_m,
        incidence_rad,
        material: Material::Concrete,
        class: 0,
        reflectivity: 0.5,
        intensity: 0.5,
        azimuth_rad: 0.0,
        elevation_rad: 0.0,
        edge_px: MAX_EDGE_PX,
    }
}

/// Grid search of a two-parameter curve: the (a, b, per-bin probs) with the
/// smallest NLL.
fn fit_curve(
    table: &QTable,
    grid_a: &[f32],
    grid_b: &[f32],
    probs: impl Fn(f32, f32) -> Vec<f64>,
) -> Option<(f32, f32, Vec<f64>)> {
    let mut best: Option<(f64, f32, f32, Vec<f64>)> = None;
    for &a in grid_a {
        for &b in grid_b {
            let p = probs(a, b);
            let nll = table.nll(&p);
            if best.as_ref().is_none_or(|x| nll < x.0) {
                best = Some((nll, a, b, p));
            }
        }
    }
    best.map(|(_, a, b, p)| (a, b, p))
}

const SOFTNESS: [f32; 9] = [0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5, 0.7, 1.0];

/// The drop probability that, on top of a `reference` drop rate, gives `rate` (0 where
/// `rate` is below it): independent drops compose as 1 - (1 - p)(1 - reference).
fn excess_drop(rate: f64, reference: f64) -> f64 {
    ((rate - reference) / (1.0 - reference).max(1e-6)).max(0.0)
}

fn round3(x: f64) -> f64 {
    (x * 1000.0).round() / 1000.0
}

/// `range_dropout`: drop rate rising with the completed range.
pub struct RangeFamily;
const RANGE_BIN_M: f32 = 1.0;
const RANGE_BINS: usize = 150;
/// A dropped pixel counts for the range curve when returns enclose it within
/// this many pixels (`Pixels::enclosure_px`).
const RANGE_ENCLOSURE_PX: u8 = super::fit::ENCLOSED_PX;

impl DropFamily for RangeFamily {
    fn id(&self) -> &'static str {
        "range_dropout"
    }
    fn bins(&self, _: &Pixels) -> usize {
        RANGE_BINS
    }
    /// Dropped pixels count only when returns enclose them closely, or they lie on
    /// a level plane (the open ground within reach, a garage's ceiling): the range an
    /// open-space pixel takes from an object's outline is the scene's, not the sensor's.
    fn bin(&self, px: &Pixels, i: usize) -> Option<usize> {
        let r = px.range_m[i];
        let level_plane = px.level_plane.get(i).copied().unwrap_or(false);
        (r.is_finite() && (px.enclosure_px[i] <= RANGE_ENCLOSURE_PX || level_plane))
            .then(|| ((r.max(0.0) / RANGE_BIN_M) as usize).min(RANGE_BINS - 1))
    }
    fn fit(&self, table: &QTable, _: &Pixels) -> Option<DropFit> {
        let grid_a: Vec<f32> = (0..40).map(|i| 5.0 * 60f32.powf(i as f32 / 39.0)).collect();
        let probs = |a: f32, b: f32| {
            let e = RangeDropout {
                enabled: true,
                range_50_m: a,
                softness: b,
            };
            (0..RANGE_BINS)
                .map(|bin| f64::from(e.drop_prob(&ray((bin as f32 + 0.5) * RANGE_BIN_M, 0.0))))
                .collect()
        };
        let (a, b, drop_prob) = fit_curve(table, &grid_a, &SOFTNESS, probs)?;
        // The range where 10 % of the rays drop: p = 0.1 <=> d = r50 · 9^(-s/2).
        let onset = a * 9f32.powf(-b / 2.0);
        Some(curve_fit(
            "range_dropout",
            [("range_50_m", a), ("softness", b)],
            drop_prob,
            format!("ranges beyond ~{onset:.0} m (10 % of rays lost there, half at {a:.0} m)"),
        ))
    }
}

/// `incidence_dropout`: drop rate rising as cos(incidence) falls.
pub struct IncidenceFamily;
const COS_BINS: usize = 50;

impl DropFamily for IncidenceFamily {
    fn id(&self) -> &'static str {
        "incidence_dropout"
    }
    fn bins(&self, _: &Pixels) -> usize {
        COS_BINS
    }
    /// Normals beyond ~89 deg (cos < 0.02) come from fill and edge artefacts
    /// more than from surfaces: left out (unknown).
    fn bin(&self, px: &Pixels, i: usize) -> Option<usize> {
        let c = px.cos_incidence[i];
        (c.is_finite() && c >= 1.0 / COS_BINS as f32)
            .then(|| ((c.min(1.0) * COS_BINS as f32) as usize).min(COS_BINS - 1))
    }
    fn fit(&self, table: &QTable, _: &Pixels) -> Option<DropFit> {
        // cos_50 from 0.03 (88 deg) to 0.6: a curve that only bites in the
        // last bin would fit the normals' artefacts.
        let grid_a: Vec<f32> = (0..40)
            .map(|i| 0.03 * 20f32.powf(i as f32 / 39.0))
            .collect();
        let probs = |a: f32, b: f32| {
            let e = IncidenceDropout {
                enabled: true,
                cos_50: a,
                softness: b,
            };
            (0..COS_BINS)
                .map(|bin| {
                    let cos = (bin as f32 + 0.5) / COS_BINS as f32;
                    f64::from(e.drop_prob(&ray(10.0, cos.acos())))
                })
                .collect()
        };
        let (a, b, drop_prob) = fit_curve(table, &grid_a, &SOFTNESS, probs)?;
        let onset_deg = (a * 9f32.powf(b)).min(1.0).acos().to_degrees();
        Some(curve_fit(
            "incidence_dropout",
            [("cos_50", a), ("softness", b)],
            drop_prob,
            format!(
                "incidence angles above ~{onset_deg:.0} deg (grazing surfaces; half the rays lost at {:.0} deg)",
                a.acos().to_degrees()
            ),
        ))
    }
}

/// The fit of a two-parameter drop curve: its parameters (rounded in the report, exact in
/// the fitted physics), per-bin drop probabilities and location in words.
fn curve_fit(id: &str, values: [(&str, f32); 2], drop_prob: Vec<f64>, location: String) -> DropFit {
    let mut params = Map::new();
    let mut effect = Map::new();
    for (name, v) in values {
        params.insert(name.into(), json!(round3(v.into())));
        effect.insert(name.into(), json!(v));
    }
    let mut physics = Map::new();
    physics.insert(id.into(), Value::Object(effect));
    DropFit {
        drop_prob,
        params,
        physics,
        n_params: 2,
        location,
    }
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

/// `self_occlusion`: blocked bottom rows per azimuth sector, the same in every
/// scan. Each sector gets a skyline (how many bottom rows are blocked) and one
/// probability, chosen by likelihood with a BIC penalty per sector.
pub struct SelfOcclusionFamily;
/// Azimuth sectors over the turn.
const SECTORS: usize = 64;
/// A blocked sector must drop at least this share of its rays.
const MIN_BLOCK_PROB: f64 = 0.4;

impl SelfOcclusionFamily {
    fn sectors(px: &Pixels) -> usize {
        SECTORS.min(px.width.max(1))
    }
    fn sector_of_column(px: &Pixels, column: usize) -> usize {
        column * Self::sectors(px) / px.width.max(1)
    }
}

impl DropFamily for SelfOcclusionFamily {
    fn azimuth_invariant(&self) -> bool {
        false
    }
    fn id(&self) -> &'static str {
        "self_occlusion"
    }
    fn bins(&self, px: &Pixels) -> usize {
        px.height * Self::sectors(px)
    }
    fn bin(&self, px: &Pixels, i: usize) -> Option<usize> {
        let row = px.row[i] as usize;
        (row >= px.height / 2)
            .then(|| row * Self::sectors(px) + Self::sector_of_column(px, px.column[i] as usize))
    }
    fn fit(&self, table: &QTable, px: &Pixels) -> Option<DropFit> {
        let (h, g_count) = (px.height, Self::sectors(px));
        if h < 2 || table.bins != h * g_count {
            return None;
        }
        let mut drop_prob = vec![0.0; table.bins];
        // Per sector: (blocked bottom rows, prob).
        let mut skyline = vec![(0usize, 0.0f64); g_count];
        for (g, sky) in skyline.iter_mut().enumerate() {
            let bin = |row: usize| row * g_count + g;
            let n: f64 = (h / 2..h)
                .map(|r| {
                    let c = table.counts(bin(r));
                    c.0 + c.1
                })
                .sum();
            if n < 1.0 {
                continue;
            }
            let mut best = (0usize, 0.0f64, 0.0f64); // (rows, prob, gain - penalty)
            for rows in 1..=h / 2 {
                let cells: Vec<usize> = (h - rows..h).map(bin).collect();
                let nll = |p: f64| cells.iter().map(|&b| table.bin_nll(b, p)).sum::<f64>();
                let (p, at_p) = golden(0.0, 0.999, 30, nll);
                let gain = nll(0.0) - at_p - n.ln();
                if p >= MIN_BLOCK_PROB && gain > best.2 {
                    best = (rows, p, gain);
                }
            }
            *sky = (best.0, best.1);
            for r in h - best.0..h {
                drop_prob[bin(r)] = best.1;
            }
        }
        let blocked = skyline.iter().filter(|s| s.0 > 0).count();
        if blocked == 0 {
            return Some(DropFit {
                drop_prob,
                params: Map::new(),
                physics: Map::new(),
                n_params: 0,
                location: "nowhere".into(),
            });
        }
        // Runs of neighbouring sectors with the same skyline and a similar
        // probability become one occlusion sector.
        let step = 360.0 / px.width.max(1) as f64;
        let az_deg = |column: usize| {
            px.column_azimuth_rad
                .get(column)
                .map_or(0.0, |a| f64::from(*a).to_degrees())
        };
        let elevation_deg = |row: usize| {
            px.row_elevation_rad
                .get(row)
                .map_or(0.0, |e| f64::from(*e).to_degrees())
        };
        let mut sectors = Vec::new();
        let mut words = Vec::new();
        let mut g = 0;
        while g < g_count {
            let (rows, p) = skyline[g];
            if rows == 0 {
                g += 1;
                continue;
            }
            let mut end = g + 1;
            let mut sum_p = p;
            while end < g_count && skyline[end].0 == rows && (skyline[end].1 - p).abs() < 0.1 {
                sum_p += skyline[end].1;
                end += 1;
            }
            let p_mean = sum_p / (end - g) as f64;
            let first_col = g * px.width / g_count;
            let last_col = end * px.width / g_count - 1;
            // Columns run from azimuth +180 deg down to -180 deg.
            let az_max = (az_deg(first_col) + 0.5 * step).min(180.0);
            let az_min = (az_deg(last_col) - 0.5 * step).max(-180.0);
            let top = h - rows;
            let el_max = if top > 0 {
                0.5 * (elevation_deg(top) + elevation_deg(top - 1))
            } else {
                90.0
            };
            sectors.push(json!({
                "azimuth_min_deg": round3(az_min),
                "azimuth_max_deg": round3(az_max),
                "elevation_max_deg": round3(el_max),
                "prob": round3(p_mean),
            }));
            words.push(format!(
                "rows {top}-{} at azimuth [{az_min:.0}, {az_max:.0}] deg ({:.0} %)",
                h - 1,
                100.0 * p_mean
            ));
            g = end;
        }
        let mut params = Map::new();
        params.insert("sectors".into(), Value::Array(sectors.clone()));
        let mut physics = Map::new();
        physics.insert("self_occlusion".into(), json!({ "sectors": sectors }));
        Some(DropFit {
            drop_prob,
            params,
            physics,
            n_params: 2 * blocked,
            location: format!("fixed region in the bottom rows: {}", words.join("; ")),
        })
    }
}

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
/// returns a sensor fires per column is not in the data. The sweep starts straight
/// ahead; its direction and where rows come from are chosen by fit too.
pub struct MotionCoverageFamily {
    /// How far the sensor moves during one sweep.
    pub motion_per_sweep_m: f32,
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
        counter_clockwise: bool,
        rows_from_elevation: bool,
    ) -> Self {
        Self {
            motion_per_sweep_m,
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
                let turned = if self.counter_clockwise { phi } else { -phi };
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
                "pixels empty where the sweep ({}, {:.2} m per sweep) moves every return away from them: {}",
                self.sweep(),
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
    use crate::diagnose::fit::ENCLOSURE_CAP_PX;

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
        let motion = MotionCoverageFamily::new(0.8, true, true);
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
        let fresh = MotionCoverageFamily::new(0.8, true, true);
        assert_eq!(motion.bins_of(&other), fresh.bins_of(&other));
        assert_eq!(motion.bins_of(&px), fresh.bins_of(&px));
        let at = fitted(&motion, &px, "rows_shift_50_half_pixels").unwrap();
        assert!((0.8..=1.3).contains(&at), "shift_50 {at}");
        let dropped = px.kept.iter().filter(|k| !**k).count();
        assert!((20..1500).contains(&dropped), "{dropped} dropped");
    }

    #[test]
    fn without_motion_every_pixel_is_covered() {
        let still = MotionCoverageFamily::new(0.0, false, true);
        let px = ground(8, |_| false, &still);
        assert!(still.bins_of(&px).iter().all(|b| *b == Some(0)));
    }

    #[test]
    fn with_beam_numbers_only_the_columns_spread() {
        let motion = MotionCoverageFamily::new(1.5, true, false);
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

    #[test]
    fn range_curve_leaves_out_drops_in_open_space() {
        // A kept pixel, a dropped one enclosed by returns 2 pixels away, and a
        // dropped one completed from an outline with nothing beyond it.
        let px = Pixels {
            range_m: vec![70.0, 70.0, 70.0],
            kept: vec![true, false, false],
            enclosure_px: vec![0, 2, 16],
            ..Default::default()
        };
        let bins: Vec<Option<usize>> = (0..3).map(|i| RangeFamily.bin(&px, i)).collect();
        assert_eq!(bins, [Some(70), Some(70), None]);
    }
}
