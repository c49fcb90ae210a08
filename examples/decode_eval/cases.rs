//! The upsampling and restoration cases: 16 -> 64 beams, 8 of 64 lines, 10 % of points
//! and 512 -> 2048 columns, each against the baselines and the library's fills.

use anyhow::Result;
use rangegan_mcap::decode::{DecodeOptions, Decoder, Fill, Quality, Sparsify, model_grid};
use rangegan_mcap::lidar::{Interpolation, SensorProfile, SurfaceRule, resample_image};
use rayon::prelude::*;
use serde_json::json;

use crate::args::Args;
use crate::baselines::{
    GRID_BASELINES, LINE_BASELINES, anchored, column_linear, nearest_in_column_then_row,
    rows_image, scattered_baselines, with_fallbacks, with_validity_of,
};
use crate::decoder;
use crate::errors::{ErrorSums, errors, summarize};
use crate::scans::Scan;

/// A library fill measured beside the baselines: `convert --upsample-method NAME` with `rule`.
pub(crate) struct Variant {
    pub(crate) name: String,
    pub(crate) fill: Fill,
    pub(crate) rule: SurfaceRule,
}

/// The library fills measured by default: the ones `convert` offers, with the shipped rule.
pub(crate) fn default_variants() -> Vec<Variant> {
    [Fill::Learned, Fill::Guided, Fill::EdgeAware]
        .into_iter()
        .map(|fill| Variant {
            name: fill.name().replace('-', "_"),
            fill,
            rule: SurfaceRule::default(),
        })
        .chain(std::iter::once(Variant {
            // Where the gain comes from: plain bilinear (IDW), but in inverse depth.
            name: "bilinear_inverse_depth".into(),
            fill: Fill::EdgeAware,
            rule: SurfaceRule {
                inverse_depth: true,
                ..SurfaceRule::ANY
            },
        }))
        .collect()
}

/// The method names of a case: `baselines` then the variants.
pub(crate) fn names(baselines: &[&str], variants: &[Variant]) -> Vec<String> {
    baselines
        .iter()
        .map(|b| b.to_string())
        .chain(variants.iter().map(|v| v.name.clone()))
        .collect()
}

/// Upsampling 16 -> 64 beams / restoration from `n_lines` of 64 rows: decode from the kept
/// rows, fill the others.
pub(crate) fn lines_case(
    args: &Args,
    scans: &[Scan],
    n_lines: usize,
    quality: Quality,
    variants: &[Variant],
) -> Result<serde_json::Value> {
    let grid512 = model_grid();
    let mut opts = DecodeOptions::new(quality);
    opts.restore = Some(Sparsify::Lines(n_lines));
    let d = decoder(&args.model, &args.encoder, opts, &args.fast_schedule)?;
    let kept = Sparsify::kept_rows(n_lines, 64);
    let per: Vec<Vec<ErrorSums>> = scans
        .par_iter()
        .enumerate()
        .map(|(i, s)| -> Result<Vec<ErrorSums>> {
            let dec = d.decode(&s.image, i as u64)?;
            let sparse = rows_image(&s.image, &kept);
            let near = resample_image(&sparse, &grid512, Interpolation::Nearest).range_m;
            let bil = resample_image(&sparse, &grid512, Interpolation::Bilinear).range_m;
            let gan_sparse = rows_image(&with_validity_of(&s.image, &dec.model.depth_m), &kept);
            let bil_gan = resample_image(&gan_sparse, &grid512, Interpolation::Bilinear).range_m;
            let (add, mul) = anchored(&dec.model.depth_m, &bil, &bil_gan);
            let filled: Vec<Vec<f32>> = variants
                .iter()
                .map(|v| dec.interpolate_restored(v.fill, &v.rule))
                .collect();
            let observed: Vec<f32> = (0..s.image.range_m.len())
                .map(|k| {
                    if kept.contains(&(k / 512)) {
                        s.image.range_m[k]
                    } else {
                        0.0
                    }
                })
                .collect();
            let column = column_linear(&observed, &s.image.angles.elevation_rad, 64, 512);
            let fallback = nearest_in_column_then_row(&observed, 64, 512);
            let baselines = [&dec.model.depth_m, &near, &bil, &column, &add, &mul];
            let preds = with_fallbacks(&baselines, &fallback, &filled, &dec.model.depth_m);
            let held = |k: usize| !kept.contains(&(k / 512));
            Ok(errors(&s.image.range_m, &preds, &held))
        })
        .collect::<Result<_>>()?;
    Ok(summarize(&per, &names(&LINE_BASELINES, variants)))
}

/// Restoration from a random 10 % of the measured pixels.
pub(crate) fn fraction_case(
    args: &Args,
    scans: &[Scan],
    variants: &[Variant],
) -> Result<serde_json::Value> {
    let mut opts = DecodeOptions::new(Quality::Fast);
    opts.restore = Some(Sparsify::Fraction(0.1));
    let d = decoder(&args.model, &args.encoder, opts, &args.fast_schedule)?;
    let per: Vec<Vec<ErrorSums>> = scans
        .par_iter()
        .enumerate()
        .map(|(i, s)| -> Result<Vec<ErrorSums>> {
            let dec = d.decode(&s.image, i as u64)?;
            let (near, idw) = scattered_baselines(&dec.observed_m, 64, 512);
            let gan_obs: Vec<f32> = dec
                .observed_m
                .iter()
                .zip(&dec.model.depth_m)
                .map(|(o, g)| if *o > 0.0 { *g } else { 0.0 })
                .collect();
            let (_, idw_gan) = scattered_baselines(&gan_obs, 64, 512);
            let (add, mul) = anchored(&dec.model.depth_m, &idw, &idw_gan);
            let filled: Vec<Vec<f32>> = variants
                .iter()
                .map(|v| dec.interpolate_restored(v.fill, &v.rule))
                .collect();
            let column = column_linear(&dec.observed_m, &s.image.angles.elevation_rad, 64, 512);
            let fallback = nearest_in_column_then_row(&dec.observed_m, 64, 512);
            let baselines = [&dec.model.depth_m, &near, &idw, &column, &add, &mul];
            let preds = with_fallbacks(&baselines, &fallback, &filled, &dec.model.depth_m);
            let held = |k: usize| dec.held_out_m[k] > 0.0;
            Ok(errors(&s.image.range_m, &preds, &held))
        })
        .collect::<Result<_>>()?;
    Ok(summarize(
        &per,
        &names(
            &[
                "gan_fast",
                "nearest",
                "idw",
                "column_linear",
                "anchored_add",
                "anchored_mul",
            ],
            variants,
        ),
    ))
}

/// Upsampling 512 -> 2048 columns on the full-resolution scans (truth: their 64 x 2048
/// projection).
pub(crate) fn columns_case(
    fast: &Decoder,
    scans: &[Scan],
    variants: &[Variant],
) -> Result<serde_json::Value> {
    let grid2048 = SensorProfile::kitti_hdl64e()
        .with_columns(2048)
        .angle_grid();
    let full: Vec<&Scan> = scans.iter().filter(|s| s.full.is_some()).collect();
    let prepared = fast.prepare(&grid2048);
    let per: Vec<Vec<ErrorSums>> = full
        .par_iter()
        .enumerate()
        .map(|(i, s)| -> Result<Vec<ErrorSums>> {
            let truth = s
                .full
                .as_ref()
                .map(|f| f.range_m.clone())
                .unwrap_or_default();
            let dec = fast.decode(&s.image, 1000 + i as u64)?;
            let dense = dec.render_prepared(&prepared);
            let near = resample_image(&s.image, &grid2048, Interpolation::Nearest).range_m;
            let bil = resample_image(&s.image, &grid2048, Interpolation::Bilinear).range_m;
            let gan512 = with_validity_of(&s.image, &dec.model.depth_m);
            let bil_gan = resample_image(&gan512, &grid2048, Interpolation::Bilinear).range_m;
            let (add, mul) = anchored(&dense.depth_m, &bil, &bil_gan);
            let filled: Vec<Vec<f32>> = variants
                .iter()
                .map(|v| dec.interpolate_on(&dense, v.fill, &v.rule))
                .collect();
            let fallback = nearest_in_column_then_row(&near, 64, 2048);
            let baselines = [&dense.depth_m, &near, &bil, &add, &mul];
            let preds = with_fallbacks(&baselines, &fallback, &filled, &dense.depth_m);
            Ok(errors(&truth, &preds, &|_| true))
        })
        .collect::<Result<_>>()?;
    Ok(summarize(&per, &names(&GRID_BASELINES, variants)))
}

/// The four upsampling / restoration cases.
pub(crate) fn sparse_cases(
    args: &Args,
    fast: &Decoder,
    scans: &[Scan],
    variants: &[Variant],
) -> Result<serde_json::Value> {
    let rows16 = lines_case(args, scans, 16, Quality::Fast, variants)?;
    eprintln!("upsample rows 16->64: {rows16}");
    let rows8 = lines_case(args, scans, 8, Quality::Fast, variants)?;
    eprintln!("restore 8 of 64 lines: {rows8}");
    let fraction = fraction_case(args, scans, variants)?;
    eprintln!("restore 10 % of points: {fraction}");
    let columns = columns_case(fast, scans, variants)?;
    eprintln!("upsample columns 512->2048: {columns}");
    Ok(json!({
        "upsample_rows_16_to_64_mae_m": rows16,
        "upsample_columns_512_to_2048_mae_m": columns,
        "restore_8_of_64_lines_mae_m": rows8,
        "restore_10_percent_points_mae_m": fraction,
    }))
}
