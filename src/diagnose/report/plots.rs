//! The numbers the report's plots show: drop rates of sim, real and the fitted model
//! against each feature ([`Curve`]), and per-pixel maps on the scan grid ([`Maps`]).

use crate::diagnose::features::ScanFeatures;
use crate::diagnose::fit::{self, Baseline, DropFamily, DropSelection, Pixels};
use crate::diagnose::residual::ResidualFit;

/// Drop rate against one feature: real, sim, and the fitted model.
#[derive(Debug, Clone, PartialEq)]
pub struct Curve {
    pub feature: &'static str,
    pub unit: &'static str,
    /// Bin centres.
    pub x: Vec<f64>,
    pub real: Vec<f64>,
    pub sim: Vec<f64>,
    pub fitted: Vec<f64>,
    /// Held-out real pixels per bin.
    pub real_pixels: Vec<f64>,
}

/// Per-pixel maps on the scan grid (row-major), for images.
#[derive(Debug, Clone, PartialEq)]
pub struct Maps {
    pub height: usize,
    pub width: usize,
    /// Drop frequency per pixel over the held-out real scans / the sim scans.
    pub real_drop: Vec<f32>,
    pub sim_drop: Vec<f32>,
    /// Extra drop probability the fitted effects add, mean over held-out scans.
    pub fitted_extra_drop: Vec<f32>,
    /// One held-out real scan: range (0 = dropped) and the located mismatch.
    pub example_range_m: Vec<f32>,
    pub example_highlight: Vec<f32>,
}

/// Binned drop rates of sim, real (held-out) and the fitted model.
pub(super) fn curves(sim: &Pixels, test: &Pixels, keep_after: &[f64]) -> Vec<Curve> {
    type Binner = fn(&Pixels, usize) -> Option<usize>;
    let specs: [(&'static str, &'static str, usize, f64, Binner); 5] = [
        ("range", "m", 32, 2.5, |p, i| {
            let r = p.range_m[i];
            r.is_finite().then(|| ((r / 2.5) as usize).min(31))
        }),
        ("incidence", "deg", 18, 5.0, |p, i| {
            let c = p.cos_incidence[i];
            c.is_finite()
                .then(|| ((c.clamp(0.0, 1.0).acos().to_degrees() / 5.0) as usize).min(17))
        }),
        ("row", "", 0, 1.0, |p, i| Some(p.row[i] as usize)),
        ("edge_distance", "px", 9, 1.0, |p, i| {
            Some(usize::from(p.edge_px.get(i).copied().unwrap_or(u8::MAX)).min(8))
        }),
        ("azimuth", "deg", 36, 10.0, |p, i| {
            let a = p
                .column_azimuth_rad
                .get(p.column[i] as usize)
                .copied()
                .unwrap_or(0.0)
                .to_degrees();
            Some((((a + 180.0) / 10.0) as usize).min(35))
        }),
    ];
    specs
        .iter()
        .map(|&(feature, unit, n, step, bin)| {
            let n = if n == 0 { test.height.max(1) } else { n };
            let mut acc = vec![[0.0f64; 5]; n]; // sim n, sim drop, real n, real drop, fitted drop
            for i in 0..sim.len() {
                if let Some(b) = bin(sim, i).filter(|&b| b < n) {
                    acc[b][0] += 1.0;
                    acc[b][1] += f64::from(u8::from(!sim.kept[i]));
                }
            }
            for (i, keep) in keep_after.iter().enumerate().take(test.len()) {
                if let Some(b) = bin(test, i).filter(|&b| b < n) {
                    acc[b][2] += 1.0;
                    acc[b][3] += f64::from(u8::from(!test.kept[i]));
                    acc[b][4] += 1.0 - keep;
                }
            }
            let x0 = if feature == "azimuth" { -180.0 } else { 0.0 };
            let centre = |b: usize| {
                if feature == "row" || feature == "edge_distance" {
                    b as f64
                } else {
                    x0 + (b as f64 + 0.5) * step
                }
            };
            let rate = |d: f64, n: f64| if n >= 20.0 { d / n } else { f64::NAN };
            Curve {
                feature,
                unit,
                x: (0..n).map(centre).collect(),
                sim: acc.iter().map(|a| rate(a[1], a[0])).collect(),
                real: acc.iter().map(|a| rate(a[3], a[2])).collect(),
                fitted: acc.iter().map(|a| rate(a[4], a[2])).collect(),
                real_pixels: acc.iter().map(|a| a[2]).collect(),
            }
        })
        .collect()
}

#[allow(clippy::too_many_arguments)]
pub(super) fn maps(
    sim: &Pixels,
    test: &Pixels,
    keep_before: &[f64],
    keep_after: &[f64],
    example: &ScanFeatures,
    families: &[&dyn DropFamily],
    selection: &DropSelection,
    baseline: &Baseline,
    reach_m: f32,
    residual: &[ResidualFit],
) -> Maps {
    let (h, w) = (test.height, test.width);
    let grid = |px: &Pixels, value: &dyn Fn(usize) -> f64| {
        let mut sum = vec![0.0f64; h * w];
        let mut n = vec![0.0f64; h * w];
        for i in 0..px.len() {
            let k = px.row[i] as usize * w + px.column[i] as usize;
            if k < sum.len() {
                sum[k] += value(i);
                n[k] += 1.0;
            }
        }
        sum.iter()
            .zip(&n)
            .map(|(s, n)| if *n > 0.0 { (s / n) as f32 } else { f32::NAN })
            .collect::<Vec<f32>>()
    };
    let real_drop = grid(test, &|i| f64::from(u8::from(!test.kept[i])));
    let sim_drop = grid(sim, &|i| f64::from(u8::from(!sim.kept[i])));
    let fitted_extra_drop = grid(test, &|i| (keep_before[i] - keep_after[i]).max(0.0));
    // The example scan: every pixel (not only those within reach).
    let px = Pixels::collect(std::slice::from_ref(example), f32::INFINITY);
    let after = fit::keep_under(families, selection, baseline, &px);
    let before: Vec<f64> = baseline
        .keep_of(&px)
        .iter()
        .map(|k| (k * selection.keep_scale).min(1.0))
        .collect();
    let mut highlight = vec![0.0f32; h * w];
    for i in 0..px.len() {
        let k = px.row[i] as usize * w + px.column[i] as usize;
        if k < highlight.len() && px.range_m[i] <= reach_m {
            highlight[k] = (before[i] - after[i]).max(0.0) as f32;
        }
    }
    if residual
        .iter()
        .any(|r| r.id == "motion_distortion" && r.significant())
    {
        for row in 0..h {
            for j in [w / 2 - 1, w / 2] {
                highlight[row * w + j] = 1.0;
            }
        }
    }
    Maps {
        height: h,
        width: w,
        real_drop,
        sim_drop,
        fitted_extra_drop,
        example_range_m: (0..example.len())
            .map(|k| {
                if example.kept[k] {
                    example.range_m[k]
                } else {
                    0.0
                }
            })
            .collect(),
        example_highlight: highlight,
    }
}
