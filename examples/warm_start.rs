//! Does each scan's pivotal tuning gain from starting at an earlier scan's tuned weights?
//! Consecutive scans of one KITTI drive, `fast` decodes at the given step counts, each scan
//! on its own (from the shared generator, stride 0) against chains with the given strides
//! (scan k starts from scan k - stride's tuned generator; the first `stride` scans from the
//! shared one). Prints the relative L1 of x_d on the measured pixels, mean over the scans and
//! over each third of them, and the decode time.
//!
//! With a sixth argument N the scans are decoded from N of their 64 rows (restoration), and it
//! also prints the MAE in meters over the held-out pixels of the GAN rendering, of the
//! default fill and of the guided one.
//!
//! With `WARMUP=S` in the environment, each chain's first scan is tuned for S steps. With
//! `RELAY=H`, one chain whose scans each start from the weights the scan before reached after
//! H of its steps (`convert --hand-off H`); the strides are then ignored. `TUNE_LR=R` sets
//! the tuning learning rate (default: `fast`'s).
//!
//!     cargo run --release --example warm_start -- ../shared/real_lidar kitti_raw_drive_d 30 33,14 0,1,4 [16]

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, Result};
use rangegan_mcap::decode::{DecodeOptions, Decoder, Fill, Quality, Sparsify};
use rangegan_mcap::lidar::{self, SensorProfile, Strategy};
use rangegan_mcap::model::data::{MAX_DEPTH_M, MIN_DEPTH_M};
use rangegan_mcap::model::weights::Model;

fn main() -> Result<()> {
    rangegan_mcap::model::tune_allocator();
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (data, drive, n, steps, strides, restore) = match args.as_slice() {
        [a, b, c, d, e] => (a, b, c, d, e, None),
        [a, b, c, d, e, f] => (a, b, c, d, e, Some(f.parse::<usize>()?)),
        _ => anyhow::bail!("usage: warm_start REAL_LIDAR DRIVE SCANS STEPS,.. STRIDE,.. [LINES]"),
    };
    let dir = PathBuf::from(data).join(drive);
    if !dir.exists() {
        eprintln!("skipped: {} not found", dir.display());
        return Ok(());
    }
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .with_context(|| format!("failed to list {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "bin"))
        .collect();
    files.sort();
    files.truncate(n.parse()?);
    let profile = SensorProfile::kitti_hdl64e().with_columns(512);
    let scans = files
        .iter()
        .map(|f| {
            let mut image = lidar::project(&lidar::kitti::read_bin(f)?, &profile, Strategy::Auto)?;
            for r in &mut image.range_m {
                if !(MIN_DEPTH_M..=MAX_DEPTH_M).contains(r) {
                    *r = 0.0;
                }
            }
            Ok(image)
        })
        .collect::<Result<Vec<_>>>()?;
    for steps in steps.split(',') {
        let mut opts = DecodeOptions::new(Quality::Fast);
        opts.schedule.set_tune_steps(steps.parse()?);
        if let Ok(lr) = std::env::var("TUNE_LR") {
            opts.schedule.tune_lr = lr.parse()?;
        }
        opts.restore = restore.map(Sparsify::Lines);
        let device = burn::tensor::Device::flex();
        // A decoder of its own for the chains' first scans only where WARMUP asks for one.
        let first = match std::env::var("WARMUP") {
            Ok(steps) => {
                let mut first_opts = opts.clone();
                first_opts.schedule.set_tune_steps(steps.parse()?);
                Some(Decoder::new(Model::load(None, &device)?, first_opts)?)
            }
            Err(_) => None,
        };
        // RELAY=h: one chain, each scan starting from the weights its predecessor reached
        // after h steps (`convert --hand-off h`); the stride is then ignored.
        let relay: Option<usize> = std::env::var("RELAY").ok().map(|h| h.parse()).transpose()?;
        let decoder = Decoder::new(Model::load(None, &device)?, opts)?;
        for stride in strides.split(',') {
            let stride: usize = stride.parse()?;
            let start = Instant::now();
            let mut tuned = Vec::new();
            let mut handed: Option<rangegan_mcap::model::generator::Generator> = None;
            let mut errors = Vec::new();
            let mut held_out = [(0.0f64, 0usize); 3];
            for (k, scan) in scans.iter().enumerate() {
                let from = match &relay {
                    Some(_) => handed.as_ref(),
                    None => (stride > 0 && k >= stride).then(|| &tuned[k - stride]),
                };
                let chain_start = stride > 0 && k < stride;
                let decoder = first.as_ref().filter(|_| chain_start).unwrap_or(&decoder);
                let decoded = match relay {
                    Some(h) => {
                        let (next, partial) = decoder.begin(scan, k as u64, from, h)?;
                        handed = Some(next);
                        decoder.finish(partial)
                    }
                    None => decoder.decode_from(scan, k as u64, from)?,
                };
                errors.push(decoded.error.unwrap_or(f32::NAN) as f64);
                if restore.is_some() {
                    for (sum, fill) in
                        held_out
                            .iter_mut()
                            .zip([Fill::Gan, Fill::DEFAULT, Fill::Guided])
                    {
                        let out = decoded.model_output(fill);
                        for (d, t) in out.depth_m.iter().zip(&decoded.held_out_m) {
                            if *t > 0.0 {
                                sum.0 += f64::from((d - t).abs());
                                sum.1 += 1;
                            }
                        }
                    }
                }
                tuned.push(decoded.tuned_generator().clone());
            }
            let mean = |e: &[f64]| e.iter().sum::<f64>() / e.len().max(1) as f64;
            let third = errors.len().div_ceil(3);
            let parts: Vec<String> = errors
                .chunks(third.max(1))
                .map(|c| format!("{:.4}", mean(c)))
                .collect();
            println!(
                "{steps} steps, stride {stride}: relative L1 {:.4} over {} scans (thirds {}), {:.1} s",
                mean(&errors),
                errors.len(),
                parts.join(" / "),
                start.elapsed().as_secs_f64()
            );
            if restore.is_some() {
                let mae: Vec<String> = held_out
                    .iter()
                    .map(|(s, n)| format!("{:.3}", s / (*n).max(1) as f64))
                    .collect();
                println!(
                    "  held-out MAE (m): GAN {}, default fill {}, guided {}",
                    mae[0], mae[1], mae[2]
                );
            }
        }
    }
    Ok(())
}
