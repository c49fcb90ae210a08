//! The `self_occlusion` family: bottom rows that the sensor's own mount or vehicle
//! blocks in some azimuth sectors, the same in every scan.

use serde_json::{Map, Value, json};

use super::round3;
use crate::diagnose::fit::{DropFamily, DropFit, Pixels, QTable, golden};

/// `self_occlusion`: blocked bottom rows per azimuth sector, the same in every
/// scan. Each sector gets a skyline (how many bottom rows are blocked) and one
/// probability, chosen by likelihood with a BIC penalty per sector.
pub struct SelfOcclusionFamily;
/// Azimuth sectors over the turn.
const SECTORS: usize = 64;
/// A blocked sector must drop at least this share of its rays.
const MIN_BLOCK_PROB: f64 = 0.4;
/// The share of the turn's sectors from which blocked bottom rows may be the lasers'.
const ALL_ROUND: f64 = 0.75;
/// ... when they lose less than this share of their rays on average.
const BODY_BLOCK_PROB: f64 = 0.9;

/// Whether a skyline (blocked bottom rows and probability per sector) is the lasers' own
/// drops rather than a body. A body hides part of the turn (KITTI's car: 214 of 360 deg in
/// its fit), or all round (a roof below the sensor) nearly every ray of the rows it hides;
/// weak or dead lasers lose a share of their rays in every direction, and `beam_dropout`
/// reads them.
fn lasers_all_round(skyline: &[(usize, f64)]) -> bool {
    let blocked: Vec<f64> = skyline.iter().filter(|s| s.0 > 0).map(|s| s.1).collect();
    let mean = blocked.iter().sum::<f64>() / blocked.len().max(1) as f64;
    blocked.len() as f64 >= ALL_ROUND * skyline.len() as f64 && mean < BODY_BLOCK_PROB
}

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
        if blocked == 0 || lasers_all_round(&skyline) {
            return Some(DropFit {
                drop_prob: vec![0.0; table.bins],
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rows_lost_in_part_all_round_are_the_lasers_and_a_body_is_not() {
        let sectors = |blocked: usize, p: f64| -> Vec<(usize, f64)> {
            (0..SECTORS)
                .map(|g| if g < blocked { (3, p) } else { (0, 0.0) })
                .collect()
        };
        // Weak bottom lasers: 40 % of their rays lost in every direction.
        assert!(lasers_all_round(&sectors(SECTORS, 0.4)));
        assert!(lasers_all_round(&sectors(SECTORS * 4 / 5, 0.6)));
        // A car behind and beside the sensor, however partial its blocks.
        assert!(!lasers_all_round(&sectors(SECTORS * 3 / 5, 0.6)));
        // A roof all round: every ray of its rows.
        assert!(!lasers_all_round(&sectors(SECTORS, 0.99)));
    }
}
