//! Which decoder `convert` runs and what it writes besides the sensor-grid channels: the
//! spatial-latent model (the default, every sensor) or the paper's global-latent GAN with
//! pivotal tuning (`--decoder gan`), from the decoding flags.

use anyhow::bail;

use super::GlobalArgs;
use super::convert::{ConvertArgs, QualityArg};
use crate::decode::amortised::TrainedEncoder;
use crate::decode::{DecodeOptions, Decoder, Quality, Sparsify};
use crate::lidar::SensorProfile;
use crate::lidar::drop_census::X_N_WEIGHT;
use crate::model::spatial::SpatialModel;
use crate::model::weights::Model;
use crate::pipeline::{DecodeOutputs, PriorUse, SpatialOutputs};

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum DecoderArg {
    /// The spatial-latent model: one forward pass per scan, every sensor.
    Spatial,
    /// The paper's global-latent GAN: encoder and pivotal tuning per scan (`--quality`).
    Gan,
}

/// The decoder a conversion runs, with its extra outputs.
pub(crate) enum Decoding {
    Spatial(SpatialModel, SpatialOutputs),
    Gan(Decoder, DecodeOutputs),
}

impl Decoding {
    /// Where the decoded channels came from, for the output's metadata.
    pub fn source(&self) -> String {
        match self {
            Decoding::Spatial(m, _) => format!("spatial: {}", m.source),
            Decoding::Gan(d, _) => d.source(),
        }
    }
}

/// The decoder and its extra outputs, from the decoding flags (`None` for `--quality off`
/// or when only `range` is written).
pub(crate) fn resolve(args: &ConvertArgs) -> anyhow::Result<Option<Decoding>> {
    if args.quality == QualityArg::Off {
        let used = args.mask_samples != 1
            || args.raw_raydrop
            || !args.upsample.is_empty()
            || !args.target_sensor.is_empty()
            || args.restore_lines.is_some()
            || args.restore_fraction.is_some();
        if used {
            bail!(
                "--upsample, --target-sensor, --restore-*, --mask-samples and --raw-raydrop need decoding; drop --quality off"
            );
        }
        return Ok(None);
    }
    if !args.channels.is_empty() && args.channels.iter().all(|c| c == "range") {
        return Ok(None); // no decoded channel chosen: nothing to decode
    }
    let restore = match (args.restore_lines, args.restore_fraction) {
        (Some(n), _) if n == 0 || n > 1024 => bail!("--restore-lines {n}: give 1 to 1024 rows"),
        (Some(n), _) => Some(Sparsify::Lines(n)),
        (_, Some(f)) if !(f > 0.0 && f <= 1.0) => {
            bail!("--restore-fraction {f}: give a fraction in (0, 1]")
        }
        (_, Some(f)) => Some(Sparsify::Fraction(f)),
        _ => None,
    };
    let target_sensors = args
        .target_sensor
        .iter()
        .map(|s| SensorProfile::resolve(s).map_err(anyhow::Error::from))
        .collect::<anyhow::Result<Vec<_>>>()?;
    if args.decoder == DecoderArg::Spatial && !args.prior_free {
        refuse_gan_flags(args)?;
        let device = burn::tensor::Device::flex();
        let model = match &args.model {
            Some(dir) => SpatialModel::load(dir, &device)?,
            None => SpatialModel::shipped(&device)?,
        };
        return Ok(Some(Decoding::Spatial(
            model,
            SpatialOutputs {
                mask_samples: args.mask_samples,
                upsample: args.upsample.clone(),
                target_sensors,
                restore,
                fill: args.upsample_method,
            },
        )));
    }
    let quality = match args.quality {
        QualityArg::Paper => Quality::Paper,
        _ => Quality::Fast,
    };
    let mut opts = DecodeOptions::new(quality);
    opts.calibrate_raydrop = !args.raw_raydrop;
    if let Some(n) = args.w_steps {
        opts.schedule.w_steps = n;
    }
    if let Some(n) = args.tune_steps {
        opts.schedule.set_tune_steps(n);
    }
    if !args.coarse_steps.is_empty() {
        let fine = args.tune_steps.unwrap_or(5);
        opts.schedule = opts.schedule.with_coarse_steps(&args.coarse_steps, fine);
    }
    if let Some(Sparsify::Lines(n)) = restore
        && n > 64
    {
        bail!("--restore-lines {n}: give 1 to 64 rows of the GAN's 64-row grid");
    }
    opts.restore = restore;
    let device = burn::tensor::Device::flex();
    let model = Model::load(args.model.as_deref(), &device)?;
    let mut decoder = Decoder::new(model, opts)?;
    if let Some(dir) = &args.encoder {
        decoder = decoder.with_encoder(TrainedEncoder::from_dir(dir, &device)?)?;
    }
    let x_n_weight = x_n_weight(args, &decoder);
    Ok(Some(Decoding::Gan(
        decoder,
        DecodeOutputs {
            mask_samples: args.mask_samples,
            upsample: args.upsample.clone(),
            target_sensors,
            fill: args.upsample_method,
            hand_off: args.hand_off,
            x_n_weight,
        },
    )))
}

/// The pivotal-tuning flags mean nothing to the spatial model's forward pass.
fn refuse_gan_flags(args: &ConvertArgs) -> anyhow::Result<()> {
    let given = [
        ("--encoder", args.encoder.is_some()),
        ("--w-steps", args.w_steps.is_some()),
        ("--tune-steps", args.tune_steps.is_some()),
        ("--coarse-steps", !args.coarse_steps.is_empty()),
        ("--hand-off", args.hand_off.is_some()),
        ("--raw-raydrop", args.raw_raydrop),
        ("--quality paper", args.quality == QualityArg::Paper),
    ];
    if let Some((flag, _)) = given.iter().find(|(_, g)| *g) {
        bail!("{flag} tunes the global-latent GAN; add --decoder gan to use it");
    }
    Ok(())
}

/// Where the GAN's model is used: nowhere with `--prior-free`; on every topic when a model is
/// named (`--model`) or the decode restores a sparse model grid, else where it covers the
/// sensor. The spatial model covers every sensor and needs no check.
pub(crate) fn prior_use(args: &ConvertArgs, decoding: &Decoding) -> Option<PriorUse> {
    let Decoding::Gan(decoder, _) = decoding else {
        return None;
    };
    Some(if args.prior_free {
        PriorUse::Never
    } else if args.model.is_some() || decoder.options().restore.is_some() {
        PriorUse::Always
    } else {
        PriorUse::WhereCovered
    })
}

/// Says, once per run, that a GAN without a ray-drop calibration gives `raydrop_prob` no
/// x_n: each recording's own drop rates stand in for it.
pub(crate) fn warn_uncalibrated(global: &GlobalArgs, decoding: Option<&Decoding>) {
    if let Some(Decoding::Gan(decoder, outputs)) = decoding
        && outputs.x_n_weight == Some(0.0)
        && !global.quiet
    {
        eprintln!(
            "warning: model {} has no ray-drop calibration (calibration.json beside its weights), so `raydrop_prob` and the masks are each recording's own drop rates, without x_n; fit one with `rangegan-mcap calibrate-raydrop --data RECORDINGS --model DIR --out DIR/calibration.json`, or take the raw x_n with --raw-raydrop",
            decoder.source()
        );
    }
}

/// The weight of the generator's x_n against each recording's own drop rates in
/// `raydrop_prob` ([`X_N_WEIGHT`]): 0 (the rates alone) for a model without a ray-drop
/// calibration, and `None` (x_n alone) for `--raw-raydrop`.
fn x_n_weight(args: &ConvertArgs, decoder: &Decoder) -> Option<f32> {
    match (args.raw_raydrop, decoder.calibration_source()) {
        (true, _) => None,
        (false, Some(_)) => Some(X_N_WEIGHT),
        (false, None) => Some(0.0),
    }
}
