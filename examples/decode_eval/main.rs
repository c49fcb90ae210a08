//! The auto-decoding numbers on held-out real KITTI scans (none used in training): reconstruction
//! error of `fast` and `paper`, upsampling (16 -> 64 beams, 512 -> 2048 columns), restoration
//! (8 of 64 lines, 10 % of points) against nearest / bilinear interpolation, and ray-drop
//! calibration. Prints a JSON report (and Markdown tables on stderr).
//!
//!     cargo run --release --example decode_eval -- --data ../shared/real_lidar \
//!         [--paper-scans 2] [--fast-scans 26] [--encoder DIR] [--model DIR] [--out eval.json]
//!         [--png docs/img/raydrop_reliability.png] [--sparse-paper-scans 4] [--only-sparse]
//!         [--tune N] [--validation kitti_raw_drive_d] [--fast-schedule ...] [--only-reconstruction]
//!         [--only-raydrop]
//!         [--reference-scans 4]
//!
//! The upsampling and restoration cases also measure the library's fills that `convert
//! --upsample-method` offers (guided, edge-aware), with MAE near (<= 30 m) and far and the
//! share of pixels more than 1 m off. `--tune N` measures a grid of surface rules on N
//! KITTI TRAINING scans (never the held-out ones) and stops; `--only-sparse` runs only the
//! upsampling and restoration cases. `--validation DRIVE` measures on every third scan of a
//! KITTI drive set aside from training instead, for choosing settings without the held-out
//! scans.
//!
//! Held out: `semantickitti_mini/00`, `/07` (every 4th point, ~512 per ring) and the
//! full-resolution `semantickitti_ssv3`, `patchworkpp` (~2010 per ring; ground truth for the
//! 512 -> 2048 column test). Scans are decoded in parallel (rayon over scans, one thread each).
//!
//! One file per part: `args`, `scans` (loading), `cases` (upsampling and
//! restoration) with `baselines` and `errors`, `raydrop` (calibration curves) and
//! `tune` (surface rules on training scans).

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use rangegan_mcap::decode::amortised::TrainedEncoder;
use rangegan_mcap::decode::{DecodeOptions, Decoded, Decoder, Quality, Schedule};
use rangegan_mcap::model::calibration::bernoulli_nll;
use rangegan_mcap::model::data::kitti_training_files;
use rangegan_mcap::model::weights::Model;
use rayon::prelude::*;
use serde_json::json;

mod args;
mod baselines;
mod cases;
mod errors;
mod raydrop;
mod scans;
mod tune;

use args::{Args, parse_args};
use cases::{default_variants, lines_case, sparse_cases};
use raydrop::{Reliability, reliability_chart};
use scans::{Scan, load_scans};
use tune::tune;

fn decoder(
    model: &Option<PathBuf>,
    encoder: &Option<PathBuf>,
    mut opts: DecodeOptions,
    fast_schedule: &Option<Schedule>,
) -> Result<Decoder> {
    let dev = burn::tensor::Device::flex();
    if let (Some(s), Quality::Fast) = (fast_schedule, opts.quality) {
        let keep_off = opts.schedule.steps() == 0;
        opts.schedule = s.clone();
        if keep_off {
            opts.schedule.w_steps = 0;
            opts.schedule.tune_steps = 0;
        }
    }
    let mut d = Decoder::new(Model::load(model.as_deref(), &dev)?, opts)?;
    if let Some(e) = encoder {
        d = d.with_encoder(TrainedEncoder::from_dir(e, &dev)?)?;
    }
    Ok(d)
}

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len().max(1) as f64
}

fn main() -> Result<()> {
    rangegan_mcap::model::tune_allocator(); // as the binary does
    let args = parse_args()?;
    if !args.data.exists() {
        eprintln!("skipped: {} not found", args.data.display());
        return Ok(());
    }
    let scans = load_scans(&args.data, args.validation.as_deref())?;
    let fast_n = args.fast_scans.min(scans.len());
    let paper_n = args.paper_scans.min(scans.len());
    eprintln!(
        "{} held-out scans ({} fast, {} paper)",
        scans.len(),
        fast_n,
        paper_n
    );
    let model_source = Model::load(args.model.as_deref(), &burn::tensor::Device::flex())?.source;
    let fast = decoder(
        &args.model,
        &args.encoder,
        DecodeOptions::new(Quality::Fast),
        &args.fast_schedule,
    )?;
    if let Some(n) = args.tune {
        return tune(&args, &fast, n);
    }
    let header = json!({
        "model": model_source,
        "encoder": args.encoder.as_ref().map_or("shipped".to_string(), |p| p.display().to_string()),
        "scans": scans.iter().map(|s| s.name.clone()).collect::<Vec<_>>(),
    });
    if args.only_sparse {
        let sparse = sparse_cases(&args, &fast, &scans[..fast_n], &default_variants())?;
        return write_report(&args, header, json!({"upsampling_and_restoration": sparse}));
    }
    let paper = decoder(
        &args.model,
        &args.encoder,
        DecodeOptions::new(Quality::Paper),
        &None,
    )?;
    let mut reference_opts = DecodeOptions::new(Quality::Paper);
    reference_opts.schedule = Schedule::reference();
    let reference = decoder(&args.model, &None, reference_opts, &None)?.without_encoder();
    let mut no_enc_opts = DecodeOptions::new(Quality::Paper);
    no_enc_opts.schedule = args.fast_schedule.clone().unwrap_or_else(Schedule::fast);
    let no_encoder = decoder(&args.model, &None, no_enc_opts, &None)?.without_encoder();
    let mut encoder_only_opts = DecodeOptions::new(Quality::Fast);
    encoder_only_opts.schedule.w_steps = 0;
    encoder_only_opts.schedule.tune_steps = 0;
    let encoder_only = decoder(&args.model, &args.encoder, encoder_only_opts, &None)?;

    // ---- Reconstruction ----------------------------------------------------------------
    // Per-scan times include waiting for a free worker; throughput is scans / wall time.
    let timed = |d: &Decoder, s: &Scan, seed: u64| -> Result<(Decoded, f64)> {
        let t = Instant::now();
        let r = d.decode(&s.image, seed)?;
        Ok((r, t.elapsed().as_secs_f64()))
    };
    let t0 = Instant::now();
    let fast_res: Vec<(Decoded, f64)> = scans[..fast_n]
        .par_iter()
        .enumerate()
        .map(|(i, s)| timed(&fast, s, i as u64))
        .collect::<Result<_>>()?;
    let fast_wall = t0.elapsed().as_secs_f64();
    let ablation: Vec<(f64, f64)> = scans[..fast_n]
        .par_iter()
        .enumerate()
        .map(|(i, s)| -> Result<(f64, f64)> {
            let a = encoder_only
                .decode(&s.image, i as u64)?
                .error
                .unwrap_or(f32::NAN);
            let b = no_encoder
                .decode(&s.image, i as u64)?
                .error
                .unwrap_or(f32::NAN);
            Ok((f64::from(a), f64::from(b)))
        })
        .collect::<Result<_>>()?;
    let decode_all = |d: &Decoder, n: usize| -> Result<(Vec<(Decoded, f64)>, f64)> {
        let t = Instant::now();
        let res = scans[..n]
            .par_iter()
            .enumerate()
            .map(|(i, s)| timed(d, s, i as u64))
            .collect::<Result<_>>()?;
        Ok((res, t.elapsed().as_secs_f64()))
    };
    let (paper_res, paper_wall) = decode_all(&paper, paper_n)?;
    let reference_n = args.reference_scans.min(scans.len());
    let (reference_res, reference_wall) = decode_all(&reference, reference_n)?;
    let err = |r: &[(Decoded, f64)]| -> Vec<f64> {
        r.iter()
            .map(|(d, _)| f64::from(d.error.unwrap_or(f32::NAN)))
            .collect()
    };
    let fast_err = err(&fast_res);
    let paper_err = err(&paper_res);
    let reference_err = err(&reference_res);
    let fast_on_paper_scans = mean(&fast_err[..paper_n.min(fast_n)]);
    let speedup = (fast_n as f64 / fast_wall) / (paper_n as f64 / paper_wall);
    let reconstruction = json!({
        "threads": rayon::current_num_threads(),
        "fast_speedup_over_paper": speedup,
        "fast": {"scans": fast_n, "rel_l1_mean": mean(&fast_err), "rel_l1_per_scan": fast_err,
                  "scans_per_sec": fast_n as f64 / fast_wall, "wall_secs": fast_wall,
                  "steps": fast.options().schedule.steps()},
        "fast_on_paper_scans": fast_on_paper_scans,
        "paper": {"scans": paper_n, "rel_l1_mean": mean(&paper_err), "rel_l1_per_scan": paper_err,
                   "scans_per_sec": paper_n as f64 / paper_wall, "wall_secs": paper_wall,
                   "steps": paper.options().schedule.steps()},
        "reference": {"scans": reference_n, "rel_l1_mean": mean(&reference_err),
                      "rel_l1_per_scan": reference_err,
                      "scans_per_sec": reference_n as f64 / reference_wall,
                      "steps": reference.options().schedule.steps()},
        "encoder_only_rel_l1": mean(&ablation.iter().map(|a| a.0).collect::<Vec<_>>()),
        "w_avg_plus_fast_steps_rel_l1": mean(&ablation.iter().map(|a| a.1).collect::<Vec<_>>()),
    });
    eprintln!("reconstruction: {reconstruction}");
    if args.only_reconstruction {
        println!("{}", serde_json::to_string_pretty(&reconstruction)?);
        return Ok(());
    }

    // ---- Ray-drop calibration (fast decodes of the full scans) ---------------------------
    let (mut rel, mut rel_raw) = (Reliability::new(10), Reliability::new(10));
    let (mut nll, mut nll_raw, mut n_pix) = (0.0f64, 0.0f64, 0usize);
    let mut rows_drop = vec![(0.0f64, 0usize); 64];
    for (s, (d, _)) in scans[..fast_n].iter().zip(&fast_res) {
        let (_, raw_logits) = d.depth_and_keep_logits(&fast);
        for (k, raw) in raw_logits.iter().enumerate() {
            let dropped = s.image.range_m[k] <= 0.0;
            let p = f64::from(d.model.drop_prob[k]).clamp(1e-4, 1.0 - 1e-4);
            nll -= if dropped { p.ln() } else { (1.0 - p).ln() };
            nll_raw += bernoulli_nll(f64::from(*raw), !dropped);
            n_pix += 1;
            rel.add(p, dropped);
            rel_raw.add(1.0 / (1.0 + f64::from(*raw).exp()), dropped);
            let row = k / s.image.width;
            rows_drop[row].0 += f64::from(u8::from(dropped));
            rows_drop[row].1 += 1;
        }
    }
    // Baselines from the training scans: one global drop rate and one per row.
    let train = rangegan_mcap::model::data::RangeDataset::from_kitti_files(
        &kitti_training_files(&args.data)?,
        512,
    )?;
    let mut row_rate = vec![(0.0f64, 0.0f64); 64];
    for i in 0..train.len() {
        for (k, v) in train.image(i).iter().enumerate() {
            let row = k / 512;
            row_rate[row].0 += f64::from(u8::from(*v <= -1.0));
            row_rate[row].1 += 1.0;
        }
    }
    let global =
        row_rate.iter().map(|r| r.0).sum::<f64>() / row_rate.iter().map(|r| r.1).sum::<f64>();
    let (mut nll_global, mut nll_row) = (0.0f64, 0.0f64);
    for s in &scans[..fast_n] {
        for k in 0..s.image.len() {
            let dropped = s.image.range_m[k] <= 0.0;
            let pr = (row_rate[k / 512].0 / row_rate[k / 512].1).clamp(1e-4, 1.0 - 1e-4);
            let pg = global.clamp(1e-4, 1.0 - 1e-4);
            let f = |p: f64| if dropped { -p.ln() } else { -(1.0 - p).ln() };
            nll_global += f(pg);
            nll_row += f(pr);
        }
    }
    // The decode above saw which pixels returned; here it sees nothing of every other
    // 32-column block (returns and drops alike), and x_n is scored on those blocks only.
    let hidden = |k: usize| (k % 512 / 32) % 2 == 1;
    let blind: Vec<(f64, f64, f64, usize)> = scans[..fast_n]
        .par_iter()
        .enumerate()
        .map(|(i, s)| -> Result<(f64, f64, f64, usize)> {
            let mut img = s.image.clone();
            for (k, r) in img.range_m.iter_mut().enumerate() {
                if hidden(k) {
                    *r = 0.0;
                }
            }
            let d = fast.decode(&img, i as u64)?;
            let (_, raw) = d.depth_and_keep_logits(&fast);
            let (mut cal, mut unc, mut row, mut n) = (0.0, 0.0, 0.0, 0);
            for k in (0..s.image.len()).filter(|k| hidden(*k)) {
                let kept = s.image.range_m[k] > 0.0;
                let keep = f64::from(1.0 - d.model.drop_prob[k]).clamp(1e-4, 1.0 - 1e-4);
                cal += bernoulli_nll((keep / (1.0 - keep)).ln(), kept);
                unc += bernoulli_nll(f64::from(raw[k]), kept);
                let pr = (row_rate[k / 512].0 / row_rate[k / 512].1).clamp(1e-4, 1.0 - 1e-4);
                row += bernoulli_nll(((1.0 - pr) / pr).ln(), kept);
                n += 1;
            }
            Ok((cal, unc, row, n))
        })
        .collect::<Result<_>>()?;
    let n_blind = blind.iter().map(|b| b.3).sum::<usize>().max(1) as f64;
    let n = n_pix.max(1) as f64;
    let calibration = json!({
        "hidden_blocks": {
            "nll_xn": blind.iter().map(|b| b.0).sum::<f64>() / n_blind,
            "nll_xn_uncalibrated": blind.iter().map(|b| b.1).sum::<f64>() / n_blind,
            "nll_per_row_rate": blind.iter().map(|b| b.2).sum::<f64>() / n_blind,
            "pixels": n_blind,
        },
        "nll_xn": nll / n, "nll_xn_uncalibrated": nll_raw / n,
        "calibration": fast.calibration_source(), "nll_global_rate": nll_global / n, "nll_per_row_rate": nll_row / n,
        "drop_rate_heldout": rows_drop.iter().map(|r| r.0).sum::<f64>() / n,
        "drop_rate_train": global,
        "reliability": rel.json(),
        "reliability_uncalibrated": rel_raw.json(),
    });
    eprintln!("calibration: {calibration}");
    if let Some(png) = &args.png {
        reliability_chart(png, &rel, &rel_raw)?;
    }
    if args.only_raydrop {
        println!("{}", serde_json::to_string_pretty(&calibration)?);
        return Ok(());
    }

    // ---- Upsampling and restoration (fast decoding from sparse observations) -------------
    let variants = default_variants();
    let sparse = sparse_cases(&args, &fast, &scans[..fast_n], &variants)?;
    // The same from `paper` decodes (minutes per scan): does a longer inversion close the gap?
    let paper_rows = if args.sparse_paper_scans > 0 {
        let n = args.sparse_paper_scans.min(scans.len());
        let r16 = lines_case(&args, &scans[..n], 16, Quality::Paper, &variants)?;
        let r8 = lines_case(&args, &scans[..n], 8, Quality::Paper, &variants)?;
        eprintln!("paper: upsample rows 16->64: {r16}; restore 8 of 64 lines: {r8}");
        json!({"upsample_rows_16_to_64_mae_m": r16, "restore_8_of_64_lines_mae_m": r8})
    } else {
        serde_json::Value::Null
    };

    let results = json!({
        "reconstruction": reconstruction,
        "calibration": calibration,
        "upsampling_and_restoration": sparse,
        "paper_decodes_of_sparse_rows": paper_rows,
    });
    write_report(&args, header, results)
}

/// Prints `header` merged with `results` as JSON (and writes it to `--out`).
fn write_report(args: &Args, header: serde_json::Value, results: serde_json::Value) -> Result<()> {
    let mut report = header;
    if let (Some(r), Some(add)) = (report.as_object_mut(), results.as_object()) {
        r.extend(add.clone());
    }
    let text = serde_json::to_string_pretty(&report)?;
    if let Some(out) = &args.out {
        std::fs::write(out, &text).with_context(|| format!("failed to write {}", out.display()))?;
    }
    println!("{text}");
    Ok(())
}
