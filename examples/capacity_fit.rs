//! What limits the generator's detail: single real scans fitted by pivotal tuning with many
//! steps, by the shipped generator and by the same generator widened at its finest levels
//! (function-preserving, `train::widen`: the new channels and Fourier pairs start at zero
//! effect and the tuning may use them). Reports the fit's relative L1 of x_d on the measured
//! pixels and on the pixels beside a depth edge (a measured 4-neighbour more than 0.3 away
//! in log depth), per scan and in the mean. Scans of the validation drive (never trained on).
//!
//!     cargo run --release --example capacity_fit -- [--data ../shared/real_lidar]
//!         [--scans 3] [--steps 500,1500] [--wide 128,64,32,32,32:64,64,32,64,64]
//!         [--wide-only]
use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use burn::tensor::Device;
use rangegan_mcap::decode::{DecodeOptions, Decoder, Quality, Schedule};
use rangegan_mcap::lidar::{self, RangeImage, SensorProfile, Strategy};
use rangegan_mcap::model::AnyGenerator;
use rangegan_mcap::model::data::kitti_validation_split;
use rangegan_mcap::model::weights::Model;
use rangegan_mcap::train::widen::{check_widening, widen_generator};
use rayon::prelude::*;

fn list(s: &str) -> Result<Vec<usize>> {
    s.split(',')
        .map(|v| v.parse().with_context(|| format!("'{v}' is not a number")))
        .collect()
}

/// The shipped model, widened to `channels` and `n_freq` when given.
fn model(wide: Option<&(Vec<usize>, Vec<usize>)>, device: &Device) -> Result<Model> {
    let mut model = Model::shipped(device)?;
    let Some((channels, n_freq)) = wide else {
        return Ok(model);
    };
    let narrow = model.config.generator.clone();
    let wider = narrow
        .clone()
        .with_channels(channels.clone())
        .with_n_freq(n_freq.clone());
    check_widening(&narrow, &wider)?;
    let AnyGenerator::Implicit(trained) = model.generator else {
        bail!("the shipped generator is not DUSty v2");
    };
    model.generator = AnyGenerator::Implicit(widen_generator(trained, wider.init(device)));
    model.config.generator = wider;
    Ok(model)
}

/// Relative L1 of `depth` against `observed` on every measured pixel and on those beside a
/// depth edge.
fn errors(observed: &RangeImage, depth: &[f32]) -> (f64, f64) {
    let (h, w) = (observed.height, observed.width);
    let r = &observed.range_m;
    let (mut all, mut n, mut edge, mut m) = (0.0f64, 0usize, 0.0f64, 0usize);
    for k in (0..h * w).filter(|&k| r[k] > 0.0 && depth[k] > 0.0) {
        let e = f64::from((depth[k] - r[k]).abs() / r[k]);
        all += e;
        n += 1;
        let beside_edge =
            lidar::holes::neighbours(k, h, w).any(|q| r[q] > 0.0 && (r[q] / r[k]).ln().abs() > 0.3);
        if beside_edge {
            edge += e;
            m += 1;
        }
    }
    (all / n.max(1) as f64, edge / m.max(1) as f64)
}

fn main() -> Result<()> {
    let mut data = PathBuf::from("../shared/real_lidar");
    let (mut scans, mut steps) = (3usize, vec![500usize, 1500]);
    let mut wide = Some((vec![128, 64, 32, 32, 32], vec![64, 64, 32, 64, 64]));
    let mut wide_only = false;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        let mut value = || args.next().with_context(|| format!("{a} needs a value"));
        match a.as_str() {
            "--data" => data = PathBuf::from(value()?),
            "--scans" => scans = value()?.parse()?,
            "--steps" => steps = list(&value()?)?,
            "--wide-only" => wide_only = true,
            "--wide" => {
                let v = value()?;
                let (c, f) = v.split_once(':').context("--wide CHANNELS:FOURIER")?;
                wide = Some((list(c)?, list(f)?));
            }
            other => bail!("unknown argument {other}"),
        }
    }
    if !data.exists() {
        eprintln!("skipped: {} not found", data.display());
        return Ok(());
    }
    let (_, files) = kitti_validation_split(&data, &["kitti_raw_drive_d".to_string()])?;
    let stride = (files.len() / scans.max(1)).max(1);
    let profile = SensorProfile::kitti_hdl64e().with_columns(512);
    let images: Vec<RangeImage> = (files.iter().step_by(stride).take(scans))
        .map(|f| {
            Ok(lidar::project(
                &lidar::kitti::read_bin(f)?,
                &profile,
                Strategy::Auto,
            )?)
        })
        .collect::<Result<_>>()?;
    let device = Device::flex();
    println!(
        "| generator | MACs / image | tuning steps | relative L1 | beside depth edges | s / scan |"
    );
    println!("|---|---|---|---|---|---|");
    let generators = if wide_only {
        vec![wide.as_ref()]
    } else {
        vec![None, wide.as_ref()]
    };
    for wide in generators {
        let m = model(wide, &device)?;
        let name = format!(
            "{:?} / {:?}",
            m.config.generator.channels, m.config.generator.n_freq
        );
        let macs = m.config.generator.macs_per_image(64, 512);
        for &n in &steps {
            let mut opts = DecodeOptions::new(Quality::Paper);
            opts.schedule = Schedule::paper();
            opts.schedule.set_tune_steps(n);
            let decoder = Decoder::new(model(wide, &device)?, opts)?;
            let t = std::time::Instant::now();
            let fits: Vec<(f64, f64)> = images
                .par_iter()
                .enumerate()
                .map(|(i, image)| {
                    let d = decoder.decode(image, i as u64 + 1)?;
                    Ok(errors(image, &d.model.depth_m))
                })
                .collect::<Result<_>>()?;
            let secs = t.elapsed().as_secs_f64() * rayon::current_num_threads() as f64
                / images.len() as f64;
            let mean =
                |f: fn(&(f64, f64)) -> f64| fits.iter().map(f).sum::<f64>() / fits.len() as f64;
            println!(
                "| {name} | {:.2} G | {n} | {:.4} | {:.4} | {secs:.0} |",
                macs as f64 / 1e9,
                mean(|e| e.0),
                mean(|e| e.1)
            );
        }
    }
    Ok(())
}
