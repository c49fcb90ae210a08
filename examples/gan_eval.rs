//! GAN quality on held-out real scans: SWD of inverse depth (paper protocol:
//! 3-level Laplacian pyramid, 7x7 patches, 128 per image per level, 4 x 128 projections)
//! between each model's samples and the held-out KITTI scans (SemanticKITTI 00 and 07), with
//! the training set's own SWD against the same scans as the floor; plus each model's keep rate
//! and a picture of samples (x_G) next to real scans; and the paper's 1-NNA (Chamfer distance
//! on 2048 farthest-point-sampled points scaled by 1/80 m; 0.5 is ideal) between as many
//! samples as held-out scans and those scans, with the training set's own as the floor; and
//! each set's diversity (per-pixel standard deviation of x_G across its scans).
//!
//! ```text
//! cargo run --release --example gan_eval -- --data ../shared/real_lidar \
//!     --cache RUN/dataset.bin --png docs/img/gan_samples.png [--seeds 3] LABEL=MODEL_DIR ...
//! ```
//! `--validation-drive kitti_raw_drive_d` (repeatable) adds that drive's scans to the held-out
//! set and leaves them out of the floor's training set: for models trained with the same
//! `--validation-drive` (and the cache built without it).
//!
//! A MODEL_DIR is a model directory (config.json + g_ema.bpk) or a training run directory;
//! `shipped` is the compiled-in model. Prints one JSON object.

use std::path::PathBuf;

use anyhow::{Context, Result};
use burn::tensor::Device;
use rangegan_mcap::model::data::{RangeDataset, kitti_heldout_files, kitti_validation_split};
use rangegan_mcap::model::metrics::{
    SwdConfig, SwdReport, one_nna, point_sets, swd_between, swd_of_model,
};
use rangegan_mcap::model::sample::{SampleOptions, sample};
use rangegan_mcap::model::weights::{Model, parse_labelled_model};
use rangegan_mcap::train::write_png;

#[derive(clap::Parser)]
struct Args {
    #[arg(long, default_value = "../shared/real_lidar")]
    data: PathBuf,
    #[arg(long)]
    cache: Option<PathBuf>,
    #[arg(long)]
    png: Option<PathBuf>,
    /// SWD repeated with this many projection/patch seeds (mean and spread reported).
    #[arg(long, default_value_t = 3)]
    seeds: u64,
    #[arg(long = "validation-drive")]
    validation_drives: Vec<String>,
    /// LABEL=MODEL_DIR (or `shipped`).
    #[arg(required = true, value_parser = parse_labelled_model)]
    models: Vec<(String, Option<PathBuf>)>,
}

/// Mean and standard deviation over seeds of the mean SWD, and the per-level means.
fn summary(reports: &[SwdReport]) -> serde_json::Value {
    let n = reports.len() as f64;
    let mean = reports.iter().map(|r| r.mean).sum::<f64>() / n;
    let std =
        (reports.iter().map(|r| (r.mean - mean).powi(2)).sum::<f64>() / (n - 1.0).max(1.0)).sqrt();
    let levels = reports[0].per_level.len();
    let per_level: Vec<f64> = (0..levels)
        .map(|l| reports.iter().map(|r| r.per_level[l]).sum::<f64>() / n)
        .collect();
    serde_json::json!({ "mean": mean, "std_over_seeds": std, "per_level": per_level })
}

/// Points per scan for 1-NNA, as in the paper.
const NNA_POINTS: usize = 2048;

/// Diversity of a set of scans: the per-pixel standard deviation across the scans of
/// x_G (network units, dropped rays at -1), averaged over pixels. A generator that
/// ignores its latent code scores near 0; real scans of different places score high.
fn pixel_std(images: &[&[f32]]) -> f64 {
    let Some(n) = images.first().map(|i| i.len()) else {
        return 0.0;
    };
    let k = images.len() as f64;
    let total: f64 = (0..n)
        .map(|p| {
            let mean = images.iter().map(|i| f64::from(i[p])).sum::<f64>() / k;
            let var = images
                .iter()
                .map(|i| (f64::from(i[p]) - mean).powi(2))
                .sum::<f64>()
                / k;
            var.sqrt()
        })
        .sum();
    total / n as f64
}

fn keep_rate(images: &[f32]) -> f64 {
    images.iter().filter(|v| **v > -1.0).count() as f64 / images.len().max(1) as f64
}

fn main() -> Result<()> {
    let args = <Args as clap::Parser>::parse();
    let device = Device::flex();
    let (train_files, validation) = kitti_validation_split(&args.data, &args.validation_drives)?;
    let mut heldout_files = kitti_heldout_files(&args.data)?;
    heldout_files.extend(validation);
    let heldout = RangeDataset::from_kitti_files(&heldout_files, 512)?;
    let train = match &args.cache {
        Some(c) if c.exists() => RangeDataset::load(c)?,
        Some(c) => {
            let ds = RangeDataset::from_kitti_files(&train_files, 512)?;
            ds.save(c)?;
            ds
        }
        None => RangeDataset::from_kitti_files(&train_files, 512)?,
    };
    let configs: Vec<SwdConfig> = (0..args.seeds.max(1))
        .map(|seed| SwdConfig {
            seed,
            ..SwdConfig::default()
        })
        .collect();
    let floor: Vec<SwdReport> = configs
        .iter()
        .map(|c| swd_between(&train, &heldout, c))
        .collect();
    // 1-NNA: as many generated (or training) scans as held-out ones, 2048 points each.
    let n = heldout.height * heldout.width;
    let heldout_points = point_sets(
        &heldout.images.chunks_exact(n).collect::<Vec<_>>(),
        &heldout.angles,
        NNA_POINTS,
    );
    let stride = (train.len() / heldout.len()).max(1);
    let train_sub: Vec<&[f32]> = (0..heldout.len())
        .map(|i| train.image(i * stride))
        .collect();
    let train_nna = one_nna(
        &point_sets(&train_sub, &train.angles, NNA_POINTS),
        &heldout_points,
    );
    let heldout_images: Vec<&[f32]> = heldout.images.chunks_exact(n).collect();
    let mut rows = vec![
        serde_json::json!({
            "label": "held-out scans", "images": heldout.len(),
            "diversity": pixel_std(&heldout_images),
        }),
        serde_json::json!({
            "label": "training set (floor)", "images": train.len(), "swd": summary(&floor),
            "keep_rate": keep_rate(&train.images), "one_nna": train_nna,
            "diversity": pixel_std(&train_sub),
        }),
    ];
    let mut picture: Vec<Vec<f32>> = Vec::new();
    for (label, dir) in &args.models {
        let model = Model::load(dir.as_deref(), &device).with_context(|| label.clone())?;
        // as many samples as training scans, so the floor and the models compare equal set sizes
        let reports = configs
            .iter()
            .map(|c| swd_of_model(&model, &heldout, train.len(), c, &device))
            .collect::<Result<Vec<_>>>()?;
        let opts = SampleOptions {
            n: 64,
            seed: 1,
            truncation: 1.0,
            grid: Some(heldout.angles.clone()),
        };
        let samples = sample(&model, &opts, &device)?;
        let x_g: Vec<Vec<f32>> = samples
            .iter()
            .take(heldout.len())
            .map(|s| {
                s.x_d
                    .iter()
                    .zip(&s.mask)
                    .map(|(x, &m)| if m { 2.0 * x - 1.0 } else { -1.0 })
                    .collect()
            })
            .collect();
        let refs: Vec<&[f32]> = x_g.iter().map(|v| v.as_slice()).collect();
        let nna = one_nna(
            &point_sets(&refs, &heldout.angles, NNA_POINTS),
            &heldout_points,
        );
        let kept =
            samples.iter().flat_map(|s| &s.mask).filter(|m| **m).count() as f64 / (64 * n) as f64;
        for s in samples.iter().take(3) {
            // x_G in network units: 2 x_d - 1 where kept, -1 (black) where dropped
            picture.push(
                s.x_d
                    .iter()
                    .zip(&s.mask)
                    .map(|(x, &m)| if m { 2.0 * x - 1.0 } else { -1.0 })
                    .collect(),
            );
        }
        rows.push(serde_json::json!({
            "label": label, "model": model.source, "arch": model.config.arch,
            "swd": summary(&reports), "keep_rate": kept, "one_nna": nna,
            "diversity": pixel_std(&refs),
        }));
    }
    if let Some(png) = &args.png {
        for i in 0..3.min(heldout.len()) {
            picture.push(heldout.image(i * heldout.len() / 3).to_vec());
        }
        let refs: Vec<&[f32]> = picture.iter().map(|p| p.as_slice()).collect();
        write_png(png, &refs, heldout.height, heldout.width)?;
    }
    println!(
        "{}",
        serde_json::to_string_pretty(&serde_json::json!({
            "heldout_images": heldout.len(), "validation_drives": args.validation_drives, "swd_config": format!("{:?}", configs[0]), "swd_seeds": configs.len(), "results": rows,
        }))?
    );
    Ok(())
}
