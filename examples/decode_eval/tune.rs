//! `--tune N`: a grid of surface rules for the guided and edge-aware fills, measured on
//! training scans (never the held-out ones).

use anyhow::Result;
use rangegan_mcap::decode::{Decoder, Fill};
use rangegan_mcap::lidar::SurfaceRule;

use crate::args::Args;
use crate::cases::{Variant, sparse_cases};
use crate::scans::load_training_scans;

/// Every rule of a small grid, for the guided and the edge-aware fill, on training scans;
/// prints each variant's MAE per case relative to the case's bilinear (IDW) baseline.
pub(crate) fn tune(args: &Args, fast: &Decoder, n: usize) -> Result<()> {
    let scans = load_training_scans(&args.data, n)?;
    eprintln!(
        "tuning on {} training scans ({} full resolution)",
        scans.len(),
        scans.iter().filter(|s| s.full.is_some()).count()
    );
    let mut variants = Vec::new();
    for inverse_depth in [false, true] {
        let inv = if inverse_depth { " 1/d" } else { "" };
        for jump_per_deg in [0.2f32, 0.3, 0.5] {
            for trust_below_deg in [0.0f32, 1.0, 1.5] {
                let jump = jump_per_deg;
                let t = trust_below_deg;
                variants.push(Variant {
                    name: format!("edge_aware j={jump} t={t}{inv}"),
                    fill: Fill::EdgeAware,
                    rule: SurfaceRule {
                        jump_per_deg,
                        trust_below_deg,
                        inverse_depth,
                        ..SurfaceRule::default()
                    },
                });
                for guide_jump in [0.1f32, 0.2, 0.3] {
                    variants.push(Variant {
                        name: format!("guided j={jump} t={t} g={guide_jump}{inv}"),
                        fill: Fill::Guided,
                        rule: SurfaceRule {
                            jump_per_deg,
                            guide_jump,
                            trust_below_deg,
                            inverse_depth,
                        },
                    });
                }
            }
        }
    }
    let cases = sparse_cases(args, fast, &scans, &variants)?;
    let keys = [
        ("upsample_rows_16_to_64_mae_m", "bilinear"),
        ("upsample_columns_512_to_2048_mae_m", "bilinear"),
        ("restore_8_of_64_lines_mae_m", "bilinear"),
        ("restore_10_percent_points_mae_m", "idw"),
    ];
    println!("| variant | 16->64 | 512->2048 | 8 lines | 10 % | mean ratio to bilinear/IDW |");
    println!("|---|---|---|---|---|---|");
    for v in &variants {
        let mut cells = Vec::new();
        let mut ratios = Vec::new();
        for (case, base) in keys {
            let mae = cases[case][&v.name]["mae"].as_f64().unwrap_or(f64::NAN);
            let b = cases[case][base]["mae"].as_f64().unwrap_or(f64::NAN);
            // Cases without ground truth on the training scans (no full-resolution ones
            // for 512 -> 2048) are left out of the mean.
            if b > 0.0 {
                ratios.push(mae / b);
            }
            cells.push(format!("{mae:.3}"));
        }
        let ratio = ratios.iter().sum::<f64>() / ratios.len().max(1) as f64;
        println!("| {} | {} | {ratio:.3} |", v.name, cells.join(" | "));
    }
    for (case, base) in keys {
        println!(
            "{case}: {base} {:.3}",
            cases[case][base]["mae"].as_f64().unwrap_or(f64::NAN)
        );
    }
    Ok(())
}
