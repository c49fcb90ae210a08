//! The likelihood of a keep model on a pixel set, and the fit of one candidate given
//! the others: pixels pooled into a [`QTable`] by (candidate bin, level of the rest of
//! the model's keep probability).

use super::{DropFamily, DropFit, Pixels};
use crate::model::calibration::bernoulli_nll;

/// Levels of `1 - q` (log scale) in a [`QTable`].
const Q_LEVELS: usize = 96;
const Q_FLOOR: f64 = 1e-5;
/// Largest keep probability a model may give (keeps logs finite).
const KEEP_MAX: f64 = 1.0 - 1e-7;

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
pub(super) fn model_keep(
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
pub(super) fn pixel_nll(kept: bool, k: f64) -> f64 {
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
pub(super) fn mask_nll_ahead_behind(px: &Pixels, keep: &[f64]) -> [f64; 2] {
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
pub(super) fn best_scale(px: &Pixels, rest: &[f64]) -> f64 {
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

/// Fits `family` on `train` given the chosen `effects` at the keep scale `c0`, or,
/// with `refit_scale`, alternating with the scale: (fit, scale).
pub(super) fn fit_given(
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
pub(super) fn fit_both(
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
}
