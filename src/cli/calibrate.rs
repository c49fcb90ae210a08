//! `rangegan-mcap calibrate-raydrop --out models/dusty2/calibration.json`: fit the per-beam
//! calibration of x_n on `fast` decodes of training scans of the model's sensor (MCAP
//! recordings or KITTI's folders; validation drives and recordings excluded, and scored
//! after the fit). `Model::from_dir` and the shipped model pick the file up beside the
//! weights.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use burn::tensor::Device;

use super::{GlobalArgs, Outcome};
use crate::decode::amortised::TrainedEncoder;
use crate::decode::calibrate::raydrop_samples;
use crate::decode::{DecodeOptions, Decoder, Quality};
use crate::model::ModelConfig;
use crate::model::calibration::{BeamCalibration, BeamSamples, RaydropCalibration};
use crate::model::weights::Model;
use crate::train::scans::{ScanSource, Scans};

#[derive(Debug, clap::Args)]
pub struct CalibrateArgs {
    /// The real scans (repeatable): MCAP recordings and folders of them, or one KITTI folder
    /// (`semantickitti_mini` etc.; sequences 00 and 07 are not used).
    #[arg(long, value_name = "PATH", required = true)]
    pub data: Vec<PathBuf>,
    /// How the recordings' clouds become range images (default `--sensor`: the model's).
    #[command(flatten)]
    pub layout: super::train::LayoutArgs,
    /// A KITTI raw drive or recording set aside: not fitted on, scored after the fit.
    #[arg(
        long,
        value_name = "DRIVE|RECORDING",
        visible_alias = "validation-recording"
    )]
    pub validation_drive: Vec<String>,
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

/// x_n's mean NLL per pixel over `samples`, before and after `calibration`, and the pixels.
fn nll(samples: &[BeamSamples], calibration: &RaydropCalibration) -> (f64, f64, usize) {
    let (mut before, mut after, mut pixels) = (0.0, 0.0, 0usize);
    for s in samples {
        before += s.nll(&BeamCalibration::IDENTITY) * s.logits.len() as f64;
        after += s.nll(&calibration.params(s.elevation_rad)) * s.logits.len() as f64;
        pixels += s.logits.len();
    }
    let n = pixels.max(1) as f64;
    (before / n, after / n, pixels)
}

pub fn run(global: &GlobalArgs, args: CalibrateArgs) -> Result<Outcome> {
    if args.scans == 0 {
        bail!("--scans must be at least 1");
    }
    let model_config = match &args.model {
        Some(dir) => ModelConfig::load(&dir.join("config.json"))?,
        None => ModelConfig::parse(crate::model::weights::SHIPPED_CONFIG)?,
    };
    let mut layout = args.layout.layout()?;
    if layout.sensor.is_none() {
        // The decode inverts on the model's grid: project straight onto it.
        layout.sensor = Some(model_config.sensor.clone());
        layout.columns = layout.columns.or(Some(model_config.sensor.columns));
    }
    let source = ScanSource {
        data: args.data.clone(),
        validation: args.validation_drive.clone(),
        layout,
    };
    let (training, validation) = source.split()?;
    let profile = source.profile(&training)?;
    let scans = source.spaced_images(&training, &profile, args.scans)?;
    if scans.is_empty() {
        bail!("no training scans in the data given");
    }
    let n = scans.len();
    let device = Device::flex();
    let model = Model::load(args.model.as_deref(), &device)?;
    let mut decoder = Decoder::new(model, DecodeOptions::new(Quality::Fast))?;
    if let Some(dir) = &args.encoder {
        decoder = decoder.with_encoder(TrainedEncoder::from_dir(dir, &device)?)?;
    }
    let samples = raydrop_samples(&decoder, &scans)?;
    let what = match training {
        Scans::Kitti(_) => "KITTI training scans".to_string(),
        Scans::Recordings(ref f) => format!("scans of {} recordings ({})", f.len(), profile.name),
    };
    let fitted_on = format!(
        "fast decodes ({} steps) of {n} {what}, {}",
        decoder.options().schedule.steps(),
        decoder.source()
    );
    let calibration = RaydropCalibration::fit(&samples, fitted_on)?;
    let (before, after, pixels) = nll(&samples, &calibration);
    let held_out = if validation.is_empty() {
        None
    } else {
        let val = source.spaced_images(&validation, &profile, args.scans)?;
        Some((
            val.len(),
            nll(&raydrop_samples(&decoder, &val)?, &calibration),
        ))
    };
    let text = serde_json::to_string_pretty(&calibration)?;
    crate::util::fs::write_atomic(&args.out, text.as_bytes())
        .with_context(|| format!("failed to write '{}'", args.out.display()))?;
    if global.json {
        let summary = serde_json::json!({
            "out": args.out.display().to_string(), "scans": n, "pixels": pixels,
            "nll_uncalibrated": before, "nll_calibrated": after,
            "validation": held_out.map(|(scans, (before, after, pixels))| serde_json::json!({
                "scans": scans, "pixels": pixels,
                "nll_uncalibrated": before, "nll_calibrated": after,
            })),
        });
        println!("{summary}");
    }
    if !global.quiet {
        eprintln!(
            "{}: {} beams from {n} scans; x_n NLL per pixel on them {before:.4} -> {after:.4}",
            args.out.display(),
            calibration.beams.len()
        );
        if let Some((scans, (before, after, _))) = held_out {
            eprintln!(
                "  held out ({scans} validation scans): x_n NLL per pixel {before:.4} -> {after:.4}"
            );
        }
    }
    Ok(Outcome::Success)
}
