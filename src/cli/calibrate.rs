//! `rangegan-mcap calibrate-raydrop --out models/dusty2/calibration.json`: fit the per-beam
//! calibration of x_n on `fast` decodes of KITTI training scans (held-out sequences excluded).
//! `Model::from_dir` and the shipped model pick the file up beside the weights.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use burn::tensor::Device;

use super::{GlobalArgs, Outcome};
use crate::decode::amortised::TrainedEncoder;
use crate::decode::calibrate::raydrop_samples;
use crate::decode::{DecodeOptions, Decoder, Quality};
use crate::lidar::{self, SensorProfile, Strategy};
use crate::model::calibration::{BeamCalibration, RaydropCalibration};
use crate::model::data::kitti_training_files;
use crate::model::weights::Model;

#[derive(Debug, clap::Args)]
pub struct CalibrateArgs {
    /// The real-data folder (`semantickitti_mini` etc.; sequences 00 and 07 are not used).
    #[arg(long, default_value = "../shared/real_lidar")]
    pub data: PathBuf,
    /// Generator (default: the shipped one).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Encoder of the fast decode (default: the shipped one).
    #[arg(long)]
    pub encoder: Option<PathBuf>,
    /// Training scans to decode, evenly spaced over the training files.
    #[arg(long, default_value_t = 64)]
    pub scans: usize,
    /// Where to write the calibration (JSON).
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(global: &GlobalArgs, args: CalibrateArgs) -> Result<Outcome> {
    let files = kitti_training_files(&args.data)?;
    if files.is_empty() || args.scans == 0 {
        bail!("no KITTI training scans under '{}'", args.data.display());
    }
    let n = args.scans.min(files.len());
    let profile = SensorProfile::kitti_hdl64e().with_columns(512);
    let scans = (0..n)
        .map(|i| {
            let path = &files[i * files.len() / n];
            let scan = lidar::kitti::read_bin(path)
                .with_context(|| format!("failed to read '{}'", path.display()))?;
            lidar::project(&scan, &profile, Strategy::Auto)
                .with_context(|| format!("failed to project '{}'", path.display()))
        })
        .collect::<Result<Vec<_>>>()?;
    let device = Device::flex();
    let model = Model::load(args.model.as_deref(), &device)?;
    let mut decoder = Decoder::new(model, DecodeOptions::new(Quality::Fast))?;
    if let Some(dir) = &args.encoder {
        decoder = decoder.with_encoder(TrainedEncoder::from_dir(dir, &device)?)?;
    }
    let samples = raydrop_samples(&decoder, &scans)?;
    let fitted_on = format!(
        "fast decodes ({} steps) of {n} KITTI training scans, {}",
        decoder.options().schedule.steps(),
        decoder.source()
    );
    let calibration = RaydropCalibration::fit(&samples, fitted_on)?;
    let (mut before, mut after, mut pixels) = (0.0, 0.0, 0usize);
    for s in &samples {
        before += s.nll(&BeamCalibration::IDENTITY) * s.logits.len() as f64;
        after += s.nll(&calibration.params(s.elevation_rad)) * s.logits.len() as f64;
        pixels += s.logits.len();
    }
    let (before, after) = (before / pixels as f64, after / pixels as f64);
    let text = serde_json::to_string_pretty(&calibration)?;
    crate::util::fs::write_atomic(&args.out, text.as_bytes())
        .with_context(|| format!("failed to write '{}'", args.out.display()))?;
    if global.json {
        let summary = serde_json::json!({
            "out": args.out.display().to_string(), "scans": n, "pixels": pixels,
            "nll_uncalibrated": before, "nll_calibrated": after,
        });
        println!("{summary}");
    }
    if !global.quiet {
        eprintln!(
            "{}: {} beams from {n} scans; x_n NLL per pixel on them {before:.4} -> {after:.4}",
            args.out.display(),
            calibration.beams.len()
        );
    }
    Ok(Outcome::Success)
}
