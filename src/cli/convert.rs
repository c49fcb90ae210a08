//! `rangegan-mcap convert IN OUT`: copy every record, add range-image channels and (unless
//! `--quality off`) the auto-decoded depth, ray-drop and completed-cloud channels.

use std::collections::BTreeMap;
use std::path::PathBuf;

use anyhow::{Context, bail};

use super::{GlobalArgs, Outcome};
use crate::decode::amortised::TrainedEncoder;
use crate::decode::{DecodeOptions, Decoder, Quality, Sparsify};
use crate::io::{McapOutput, OnError};
use crate::lidar::{SensorProfile, Strategy};
use crate::model::weights::Model;
use crate::pipeline::{self, ConvertOptions, DecodeOutputs, DecodeStage, SensorChoice, Stage};

#[derive(Debug, clap::Args)]
pub struct ConvertArgs {
    /// Input MCAP recording (never modified).
    pub input: PathBuf,
    /// Output MCAP (written to a temporary file and renamed when complete).
    pub output: PathBuf,
    /// Point-cloud topics to process (repeatable); default: every point-cloud topic.
    #[arg(long)]
    pub topic: Vec<String>,
    /// Sensor profile: `auto`, a built-in name (hdl64e, hdl32e, vlp16, vlp32c,
    /// os1-32, os1-64, os1-128), or a profile / Ouster metadata JSON file.
    #[arg(long, default_value = "auto")]
    pub sensor: String,
    /// Range-image columns (default: the sensor profile's).
    #[arg(long)]
    pub columns: Option<usize>,
    /// How a point's row is found (default: chosen from the data).
    #[arg(long, value_enum, default_value = "auto")]
    pub projection: Strategy,
    /// What to do with a corrupt chunk.
    #[arg(long, value_enum, default_value = "fail")]
    pub on_error: OnError,
    /// Exit non-zero (3) when anything was skipped or unreadable (truncated input,
    /// skipped chunks, undecodable point clouds), and keep no file at OUT then.
    #[arg(long)]
    pub strict: bool,
    /// Overwrite an existing OUT.
    #[arg(long)]
    pub force: bool,
    /// Auto-decoding with the range-image GAN: `fast` (amortised encoder + 14 pivotal-tuning
    /// steps), `paper` (the paper's 1000-step pivotal tuning inversion, minutes per scan) or
    /// `off` (range images only).
    #[arg(long, value_enum, default_value = "fast")]
    pub quality: QualityArg,
    /// Generator: a model directory (config.json + g_ema.bpk) or a training run directory
    /// (default: the shipped weights).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Encoder of `--quality fast`: a `train-encoder` run or model directory (default: the
    /// shipped weights).
    #[arg(long)]
    pub encoder: Option<PathBuf>,
    /// Override the optimisation steps on w (fast: 0, paper: 500).
    #[arg(long)]
    pub w_steps: Option<usize>,
    /// Override the pivotal-tuning steps on the generator weights (fast: 14, paper: 500).
    #[arg(long)]
    pub tune_steps: Option<usize>,
    /// Write the generator's own x_n, without the per-beam calibration shipped with the model
    /// (`calibration.json`; `rangegan-mcap calibrate-raydrop` fits one).
    #[arg(long)]
    pub raw_raydrop: bool,
    /// Bernoulli ray-drop masks written per scan (`raydrop_mask`, `raydrop_mask_1`, ...).
    #[arg(long, default_value_t = 1)]
    pub mask_samples: usize,
    /// Also render the decoded scene on the model grid upsampled by these factors, e.g.
    /// `2,4` -> `depth_128x1024`, `points_128x1024`, `depth_256x2048`, `points_256x2048`.
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
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum QualityArg {
    Fast,
    Paper,
    Off,
}

/// The decoder and its extra outputs, from the decoding flags (`None` for `--quality off`).
fn resolve_decoding(args: &ConvertArgs) -> anyhow::Result<Option<(Decoder, DecodeOutputs)>> {
    let quality = match args.quality {
        QualityArg::Off => {
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
        QualityArg::Fast => Quality::Fast,
        QualityArg::Paper => Quality::Paper,
    };
    let mut opts = DecodeOptions::new(quality);
    opts.calibrate_raydrop = !args.raw_raydrop;
    if let Some(n) = args.w_steps {
        opts.schedule.w_steps = n;
    }
    if let Some(n) = args.tune_steps {
        opts.schedule.tune_steps = n;
    }
    opts.restore = match (args.restore_lines, args.restore_fraction) {
        (Some(n), _) if n == 0 || n > 64 => bail!("--restore-lines {n}: give 1 to 64 rows"),
        (Some(n), _) => Some(Sparsify::Lines(n)),
        (_, Some(f)) if !(f > 0.0 && f <= 1.0) => {
            bail!("--restore-fraction {f}: give a fraction in (0, 1]")
        }
        (_, Some(f)) => Some(Sparsify::Fraction(f)),
        _ => None,
    };
    let device = burn::tensor::Device::flex();
    let model = Model::load(args.model.as_deref(), &device)?;
    let mut decoder = Decoder::new(model, opts)?;
    if let (Some(dir), Quality::Fast) = (&args.encoder, quality) {
        decoder = decoder.with_encoder(TrainedEncoder::from_dir(dir, &device)?)?;
    }
    let target_sensors = args
        .target_sensor
        .iter()
        .map(|s| SensorProfile::resolve(s).map_err(anyhow::Error::from))
        .collect::<anyhow::Result<Vec<_>>>()?;
    Ok(Some((
        decoder,
        DecodeOutputs {
            mask_samples: args.mask_samples,
            upsample: args.upsample.clone(),
            target_sensors,
        },
    )))
}

/// Resolves the sensor argument shared by several subcommands.
pub(crate) fn sensor_choice(sensor: &str) -> anyhow::Result<SensorChoice> {
    Ok(if sensor == "auto" {
        SensorChoice::Auto
    } else {
        SensorChoice::Fixed(SensorProfile::resolve(sensor)?)
    })
}

pub fn run(global: &GlobalArgs, args: ConvertArgs) -> anyhow::Result<Outcome> {
    crate::io::writer::refuse_overwriting_inputs(&args.output, &[&args.input])?;
    if let Some(c) = args.columns {
        crate::lidar::profile::check_columns(c).map_err(anyhow::Error::msg)?;
    }
    let file = std::fs::File::open(&args.input)
        .with_context(|| format!("cannot open {}", args.input.display()))?;
    let len = file.metadata().ok().map(|m| m.len());
    let decoding = resolve_decoding(&args)?;
    let mut metadata = BTreeMap::from([
        ("tool".to_string(), "rangegan-mcap".to_string()),
        ("version".to_string(), env!("CARGO_PKG_VERSION").to_string()),
        (
            "args".to_string(),
            std::env::args().skip(1).collect::<Vec<_>>().join(" "),
        ),
        ("input".to_string(), args.input.display().to_string()),
    ]);
    if let Some((decoder, _)) = &decoding {
        // What made the decoded channels, so a regenerated dataset says which weights it used.
        let schedule = &decoder.options().schedule;
        metadata.extend([
            ("decode_model".to_string(), decoder.source.clone()),
            (
                "decode_steps".to_string(),
                format!("{} w + {} tuning", schedule.w_steps, schedule.tune_steps),
            ),
            (
                "raydrop_calibration".to_string(),
                decoder.calibration_source().unwrap_or("none").to_string(),
            ),
        ]);
    }
    let opts = ConvertOptions {
        topics: (!args.topic.is_empty()).then(|| args.topic.clone()),
        sensor: sensor_choice(&args.sensor)?,
        columns: args.columns,
        strategy: args.projection,
        on_error: args.on_error,
        metadata,
        strict: args.strict,
        ..ConvertOptions::default()
    };
    let decode_stage = match &decoding {
        Some((decoder, outputs)) => Some(DecodeStage::new(decoder, outputs)?),
        None => None,
    };
    let out = McapOutput::create(&args.output, args.force)?;

    let bar = super::progress_bar(global, len.unwrap_or(0));
    let started = std::time::Instant::now();
    let decode_fn = |input: &pipeline::ScanInput<'_>| match &decode_stage {
        Some(s) => s.run(input),
        None => Ok(Vec::new()),
    };
    let stages: [&Stage<'_>; 2] = [&pipeline::range_stage, &decode_fn];
    let reader = std::io::BufReader::with_capacity(1 << 20, file);
    let report = pipeline::convert(&args.input, reader, len, out, &opts, &stages, |p| {
        bar.set_position(p.bytes_read);
        let secs = started.elapsed().as_secs_f64().max(1e-3);
        bar.set_message(format!(
            "{} scans, {:.1} scans/s",
            p.scans,
            p.scans as f64 / secs
        ));
    })?;
    bar.finish_and_clear();
    let secs = started.elapsed().as_secs_f64();

    for w in &report.warnings {
        if !global.quiet {
            eprintln!("warning: {}", w.message);
        }
    }
    super::warn_read_damage(&args.input, &report.read);
    if report.records_in.messages == 0 {
        eprintln!(
            "warning: {}: no message could be read{}",
            args.input.display(),
            if report.read.damaged() {
                " (see above)"
            } else {
                "; the recording is empty"
            }
        );
    }
    if let Some(why) = &report.read.stopped {
        eprintln!(
            "warning: {}: {why}; {} bytes after the last complete record could not be read (every complete message was processed)",
            args.input.display(),
            report.read.unread_bytes
        );
    }
    if report.copied.orphan_messages > 0 {
        eprintln!(
            "warning: {}: {} messages on channels that were never defined were dropped",
            args.input.display(),
            report.copied.orphan_messages
        );
    }
    let scans: u64 = report.topics.values().map(|t| t.scans).sum();
    let malformed: u64 = report.topics.values().map(|t| t.malformed).sum();
    if global.json {
        let summary = serde_json::json!({ "input": args.input, "output": args.output, "seconds": secs, "report": report });
        println!("{}", serde_json::to_string_pretty(&summary)?);
    }
    if !global.quiet {
        eprintln!(
            "{} -> {}: {} records copied, {} scans on {} topics -> {} new messages, {} malformed, {:.1} MB/s, {:.1} scans/s",
            args.input.display(),
            args.output.display(),
            report.copied.messages
                + report.copied.schemas
                + report.copied.channels
                + report.copied.attachments
                + report.copied.metadata,
            scans,
            report.topics.len(),
            report.outputs_written,
            malformed,
            report.read.bytes_read as f64 / 1e6 / secs.max(1e-9),
            scans as f64 / secs.max(1e-9),
        );
    }
    Ok(if report.skipped_anything() && args.strict {
        eprintln!(
            "{}: not written (--strict: input was skipped or unreadable)",
            args.output.display()
        );
        Outcome::DataSkipped
    } else {
        Outcome::Success
    })
}
