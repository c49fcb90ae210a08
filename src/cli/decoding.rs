//! Which decoder `convert` runs and what it writes besides the sensor-grid channels: the
//! spatial-latent model (the default, every sensor) or the paper's global-latent GAN with
//! pivotal tuning (`--decoder gan`), from the decoding flags.

use std::path::PathBuf;

use anyhow::bail;

use super::GlobalArgs;
use crate::decode::Fill;
use crate::decode::amortised::TrainedEncoder;
use crate::decode::{DecodeOptions, Decoder, Quality, Sparsify};
use crate::lidar::SensorProfile;
use crate::lidar::drop_census::X_N_WEIGHT;
use crate::model::spatial::SpatialModel;
use crate::model::weights::Model;
use crate::pipeline::{DecodeOutputs, PriorUse, SpatialOutputs};

/// The decoding flags of `convert`.
#[derive(Debug, clap::Args)]
pub struct DecodeArgs {
    /// Which model decodes: `spatial` (the default: the spatial-latent model, one forward
    /// pass per scan, every sensor on its own grid) or `gan` (the paper's global-latent
    /// generator, auto-decoded per scan by an encoder and pivotal tuning; `--quality`).
    #[arg(long, value_enum, default_value = "spatial")]
    pub decoder: DecoderArg,
    /// Auto-decoding: `fast`, `off` (range images only), or with `--decoder gan` also `paper`
    /// (`fast`: amortised encoder + 33 pivotal-tuning steps; `paper`: encoder + 500 steps,
    /// seconds per scan).
    #[arg(long, value_enum, default_value = "fast")]
    pub quality: QualityArg,
    /// The model: a spatial model directory (config.json and spatial.bpk, or a `train-spatial`
    /// run's `export/` or `best/`), or with `--decoder gan` a generator directory (config.json
    /// and g_ema.bpk) or a GAN training run. Default: the shipped weights. The shipped GAN is
    /// used only on topics whose sensor it covers; other topics get prior-free channels.
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Encoder that starts each decode: a `train-encoder` run or model directory (default: the
    /// shipped weights).
    #[arg(long)]
    pub encoder: Option<PathBuf>,
    /// Override the optimisation steps on w after the encoder (default 0; at most 100 000).
    #[arg(long, value_parser = super::steps())]
    pub w_steps: Option<usize>,
    /// Override the pivotal-tuning steps on the generator weights (fast: 33, paper: 500; at
    /// most 100 000).
    #[arg(long, value_parser = super::steps())]
    pub tune_steps: Option<usize>,
    /// Tune coarse to fine first: steps at 1/8, 1/4 and 1/2 of the model grid's resolution
    /// (coarsest first, e.g. `48,48,4`), each a fraction of a full-resolution step's cost; the
    /// `--tune-steps` that follow (default 5) then decay their rate to 0.
    #[arg(long, value_delimiter = ',', value_parser = super::steps())]
    pub coarse_steps: Vec<usize>,
    /// Chain each topic's scans: scan k's pivotal tuning starts from the weights scan k - N
    /// hands on (0: every scan from the shared generator). Consecutive scans see nearly the
    /// same scene, so a chain fits each scan better in the same steps (docs/decode.md); N
    /// chains per topic decode in parallel. The output depends on N, never on the threads.
    #[arg(long, default_value_t = crate::pipeline::DEFAULT_CHAIN_STRIDE,
          value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(0..=1024))]
    pub chain_stride: usize,
    /// The tuning step after which a chained scan hands its weights on to the chain's next
    /// scan, which starts tuning while this one goes on (default: after all of them, so the
    /// next scan starts from this one's final weights). With `--chain-stride 1 --hand-off 16`
    /// one chain keeps two cores busy (docs/decode.md).
    #[arg(long, value_parser = super::steps())]
    pub hand_off: Option<usize>,
    /// Write the generator's own x_n, without the per-beam calibration shipped with the model
    /// (`calibration.json`; `rangegan-mcap calibrate-raydrop` fits one).
    #[arg(long)]
    pub raw_raydrop: bool,
    /// Bernoulli ray-drop masks written per scan (`raydrop_mask`, `raydrop_mask_1`, ...),
    /// at most 64.
    #[arg(long, default_value_t = 1,
          value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(0..=64))]
    pub mask_samples: usize,
    /// Also write the scan on its sensor's grid upsampled by these factors (beams and
    /// columns), named by the grid's size: `2,4` on a 64 x 512 scan -> `depth_128x1024`,
    /// `points_128x1024`, `depth_256x2048`, `points_256x2048`.
    #[arg(long, value_delimiter = ',')]
    pub upsample: Vec<usize>,
    /// Also render it on another sensor's grid (built-in name or profile JSON), e.g.
    /// `vlp32c` -> `depth_vlp32c`, `points_vlp32c` (repeatable).
    #[arg(long)]
    pub target_sensor: Vec<String>,
    /// Decode from only N evenly spaced rows of the 64-row model grid (restoration).
    #[arg(long, conflicts_with = "restore_fraction")]
    pub restore_lines: Option<usize>,
    /// Decode from a random fraction (0..1) of the measured points (restoration).
    #[arg(long)]
    pub restore_fraction: Option<f32>,
    /// What the `--upsample` and `--target-sensor` grids and a `--restore-*` depth hold:
    /// `learned` (the default: as `edge-aware`, then rows restored between kept beams moved
    /// along their rays by a small network trained on KITTI), `edge-aware` (measured returns
    /// kept, new pixels interpolated only from neighbouring returns on their own surface;
    /// from scattered points a local inverse-depth plane where one fits), `guided` (the same,
    /// the decoded scene picking the surface where it clearly can), `bilinear`
    /// (inverse-distance weighting for scattered points), `nearest`, or `gan` (the decoded
    /// scene's rendering). Where no observed return reaches, the rendering fills in.
    #[arg(long, value_enum, default_value_t = Fill::DEFAULT)]
    pub upsample_method: Fill,
    /// Prior-free channels on every topic, whatever model covers its sensor: `depth` the
    /// completion of each scan's own returns, `raydrop_prob` the recording's own drop rates,
    /// no `x_d`. Several times faster than decoding; what a sensor no model covers gets.
    #[arg(long, conflicts_with_all = ["model", "restore_lines", "restore_fraction"])]
    pub prior_free: bool,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum QualityArg {
    Fast,
    Paper,
    Off,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum DecoderArg {
    /// The spatial-latent model: one forward pass per scan, every sensor.
    Spatial,
    /// The paper's global-latent GAN: encoder and pivotal tuning per scan (`--quality`).
    Gan,
}

/// The decoder a conversion runs, with its extra outputs.
pub(crate) enum Decoding {
    Spatial(Box<SpatialModel>, SpatialOutputs),
    Gan(Box<Decoder>, DecodeOutputs),
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
pub(crate) fn resolve(args: &DecodeArgs, channels: &[String]) -> anyhow::Result<Option<Decoding>> {
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
    if !channels.is_empty() && channels.iter().all(|c| c == "range") {
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
    // Each target grid is written as `depth_<name>`: two profiles of one name would share a
    // channel, two images per scan at one log time.
    for (i, p) in target_sensors.iter().enumerate() {
        if let Some(j) = (0..i).find(|&j| target_sensors[j].name == p.name) {
            bail!(
                "--target-sensor {} and --target-sensor {} are both named '{}': their grids \
                 would share the channels depth_{name}/points_{name}; give one of the profiles \
                 another \"name\"",
                args.target_sensor[j],
                args.target_sensor[i],
                p.name,
                name = p.name,
            );
        }
    }
    if args.decoder == DecoderArg::Spatial && !args.prior_free {
        refuse_gan_flags(args)?;
        let device = burn::tensor::Device::flex();
        let model = match &args.model {
            Some(dir) => SpatialModel::load(dir, &device)?,
            None => SpatialModel::shipped(&device)?,
        };
        return Ok(Some(Decoding::Spatial(
            Box::new(model),
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
        Box::new(decoder),
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
fn refuse_gan_flags(args: &DecodeArgs) -> anyhow::Result<()> {
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
pub(crate) fn prior_use(args: &DecodeArgs, decoding: &Decoding) -> Option<PriorUse> {
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
fn x_n_weight(args: &DecodeArgs, decoder: &Decoder) -> Option<f32> {
    match (args.raw_raydrop, decoder.calibration_source()) {
        (true, _) => None,
        (false, Some(_)) => Some(X_N_WEIGHT),
        (false, None) => Some(0.0),
    }
}
