//! `rangegan-mcap convert IN OUT`: copy every record, add range-image channels and (unless
//! `--quality off`) the auto-decoded depth, ray-drop and completed-cloud channels. One file
//! here; several files or folders go to [`super::convert_dataset`], which converts each
//! file with the same [`FileConverter`].

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

use anyhow::{Context, bail};
use clap::ValueEnum;

use super::decoding::{self, DecodeArgs, Decoding, QualityArg};
use super::{GlobalArgs, Outcome};
use crate::dataset::manifest::{self, Counts};
use crate::io::{McapOutput, OnError, WriterSettings};
use crate::lidar::{SensorProfile, Strategy};
use crate::pipeline::{
    self, ConvertOptions, ConvertReport, DecodeStage, SensorChoice, SpatialStage, StageOutput,
    Staged,
};

#[derive(Debug, clap::Args)]
pub struct ConvertArgs {
    /// Input MCAP recordings, or folders searched for `*.mcap` (never modified).
    #[arg(required = true, num_args = 1..)]
    pub inputs: Vec<PathBuf>,
    /// Output MCAP (written to a temporary file and renamed when complete); with several
    /// inputs or a folder, the output folder, where each output keeps its input's relative
    /// path and `rangegan-manifest.jsonl` records every file.
    pub output: PathBuf,
    /// Point-cloud topics to process (repeatable); default: every point-cloud topic.
    #[arg(long)]
    pub topic: Vec<String>,
    #[arg(long, default_value = "auto", help = SENSOR_HELP)]
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
    /// Overwrite an existing OUT; for folders, convert every file again even when the
    /// manifest says its output is up to date.
    #[arg(long)]
    pub force: bool,
    /// Channels to write, comma-separated (default: all): `range`, and with decoding
    /// `depth`, `raydrop_prob`, `raydrop_mask`, `points` and the `depth_*` / `points_*` of
    /// `--upsample` / `--target-sensor`. Without a decoded channel nothing is decoded.
    #[arg(long, value_delimiter = ',')]
    pub channels: Vec<String>,
    /// Output chunk size in bytes (before compression).
    #[arg(long, default_value_t = 4 * 1024 * 1024)]
    pub chunk_size: u64,
    /// Output chunk compression.
    #[arg(long, value_enum, default_value = "zstd")]
    pub compression: CompressionArg,
    #[command(flatten)]
    pub dataset: DatasetArgs,
    #[command(flatten)]
    pub decode: DecodeArgs,
}

/// Flags of dataset mode (several inputs, a folder, or an existing output folder).
#[derive(Debug, clap::Args)]
pub struct DatasetArgs {
    /// Files converted at once; the threads (`--threads`, default one per core) are split
    /// between them and the scans inside each file. Outputs are the same bytes whatever N
    /// (1 to 1024).
    #[arg(long, default_value_t = 1,
          value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..=1024))]
    pub jobs: usize,
    /// Convert only shard I of N (0-based, e.g. `--shard 3/8`): a fixed subset chosen by a
    /// hash of each file's relative path, so N machines each run one shard into a shared
    /// OUT; each writes `rangegan-manifest.shard-I-of-N.jsonl`.
    #[arg(long)]
    pub shard: Option<String>,
    /// List each file with what a run would do (convert, or skip as up to date) and stop.
    #[arg(long)]
    pub dry_run: bool,
}

impl DatasetArgs {
    /// The flags that only mean something for a dataset.
    pub fn refuse_in_one_file_form(&self) -> anyhow::Result<()> {
        if self.shard.is_some() || self.dry_run || self.jobs != 1 {
            bail!(
                "--shard, --dry-run and --jobs convert datasets: give a folder, several inputs or an existing output folder"
            );
        }
        Ok(())
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum CompressionArg {
    Zstd,
    Lz4,
    None,
}

/// The help of the `--sensor` flag of the commands that project recordings.
pub(crate) const SENSOR_HELP: &str = "Sensor profile: `auto` (estimated from the first scan), a built-in name (hdl64e, hdl32e, vlp16, vlp32c, vls128, pandar64, pandarxt32; Ouster os0-N, os1-N (gen 2), os1-N-gen1, os2-N with N beams), or a profile / Ouster metadata JSON file (a unit's own beam angles)";

/// Resolves the sensor argument shared by several subcommands.
pub(crate) fn sensor_choice(sensor: &str) -> anyhow::Result<SensorChoice> {
    Ok(if sensor == "auto" {
        SensorChoice::Auto
    } else {
        SensorChoice::Fixed(SensorProfile::resolve(sensor)?)
    })
}

/// A value's name on the command line.
fn flag_value(v: &impl ValueEnum) -> String {
    v.to_possible_value()
        .map(|p| p.get_name().to_string())
        .unwrap_or_default()
}

/// Every setting that changes the output bytes, as one normalised command line: written into
/// each output's metadata and the manifest, and compared by reruns. Paths of the recordings,
/// threads, jobs and shards are left out: they do not change any output.
pub(crate) fn output_settings(args: &ConvertArgs) -> String {
    // A flag that names a file (or a model folder) is recorded with a digest of it, so a
    // rerun after the file changed under the same name is not "up to date".
    let named = |value: &str| match crate::dataset::manifest::path_digest(Path::new(value)) {
        Some(digest) => format!("{value}@{digest}"),
        None => value.to_string(),
    };
    let mut parts = vec![
        format!("--decoder {}", flag_value(&args.decode.decoder)),
        format!("--quality {}", flag_value(&args.decode.quality)),
        format!("--sensor {}", named(&args.sensor)),
        format!("--projection {}", flag_value(&args.projection)),
        format!("--on-error {}", flag_value(&args.on_error)),
        format!("--compression {}", flag_value(&args.compression)),
        format!("--chunk-size {}", args.chunk_size),
    ];
    parts.extend(args.topic.iter().map(|t| format!("--topic {t}")));
    let optional = [
        ("--columns", args.columns.map(|v| v.to_string())),
        (
            "--model",
            args.decode
                .model
                .as_ref()
                .map(|p| named(&p.display().to_string())),
        ),
        (
            "--encoder",
            args.decode
                .encoder
                .as_ref()
                .map(|p| named(&p.display().to_string())),
        ),
        ("--w-steps", args.decode.w_steps.map(|v| v.to_string())),
        (
            "--tune-steps",
            args.decode.tune_steps.map(|v| v.to_string()),
        ),
        ("--hand-off", args.decode.hand_off.map(|v| v.to_string())),
        (
            "--restore-lines",
            args.decode.restore_lines.map(|v| v.to_string()),
        ),
        (
            "--restore-fraction",
            args.decode.restore_fraction.map(|v| v.to_string()),
        ),
    ];
    for (flag, value) in optional {
        if let Some(v) = value {
            parts.push(format!("{flag} {v}"));
        }
    }
    if args.decode.quality != QualityArg::Off {
        parts.push(format!("--mask-samples {}", args.decode.mask_samples));
    }
    if args.decode.quality != QualityArg::Off {
        parts.push(format!("--chain-stride {}", args.decode.chain_stride));
    }
    if args.decode.raw_raydrop {
        parts.push("--raw-raydrop".into());
    }
    if args.decode.prior_free {
        parts.push("--prior-free".into());
    }
    if args.decode.quality != QualityArg::Off {
        parts.push(format!(
            "--upsample-method {}",
            flag_value(&args.decode.upsample_method)
        ));
    }
    let list = |v: &[String]| v.join(",");
    let numbers = |v: &[usize]| v.iter().map(|f| f.to_string()).collect::<Vec<_>>();
    for (flag, values) in [
        ("--upsample", numbers(&args.decode.upsample)),
        ("--coarse-steps", numbers(&args.decode.coarse_steps)),
        (
            "--target-sensor",
            args.decode.target_sensor.iter().map(|t| named(t)).collect(),
        ),
        ("--channels", args.channels.clone()),
    ] {
        if !values.is_empty() {
            parts.push(format!("{flag} {}", list(&values)));
        }
    }
    parts.join(" ")
}

/// The writer settings of `--compression` and `--chunk-size`.
fn writer_settings(args: &ConvertArgs) -> anyhow::Result<WriterSettings> {
    if args.chunk_size == 0 {
        bail!("--chunk-size must be > 0 bytes");
    }
    Ok(WriterSettings {
        compression: match args.compression {
            CompressionArg::Zstd => Some(mcap::Compression::Zstd),
            CompressionArg::Lz4 => Some(mcap::Compression::Lz4),
            CompressionArg::None => None,
        },
        chunk_size: Some(args.chunk_size),
    })
}

/// Whether a stage output belongs to one of the `--channels` (`raydrop_mask` covers
/// `raydrop_mask_1`, ...).
fn channel_selected(channels: &[String], suffix: &str) -> bool {
    channels.is_empty()
        || channels.iter().any(|c| {
            c == suffix
                || (c == "raydrop_mask"
                    && suffix
                        .strip_prefix("raydrop_mask_")
                        .is_some_and(|n| n.parse::<usize>().is_ok()))
        })
}

/// What progress bars read while files convert: bytes read and scans whose stages finished
/// (counted before their batch is written), over every file of a run.
#[derive(Debug, Default)]
pub(crate) struct Counters {
    pub bytes: AtomicU64,
    pub scans: Arc<AtomicU64>,
    pub files_done: AtomicU64,
}

/// Draws `bar` from `counters` every 100 ms while `work` runs (scans advance while a batch
/// decodes, not only when it is written).
pub(crate) fn with_progress<R>(
    bar: &indicatif::ProgressBar,
    counters: &Counters,
    files: Option<usize>,
    work: impl FnOnce() -> R,
) -> R {
    let started = std::time::Instant::now();
    let stop = AtomicBool::new(false);
    let draw = || {
        bar.set_position(counters.bytes.load(Ordering::Relaxed));
        let scans = counters.scans.load(Ordering::Relaxed);
        let secs = started.elapsed().as_secs_f64().max(1e-3);
        let files = files.map_or(String::new(), |n| {
            format!(
                "{}/{n} files, ",
                counters.files_done.load(Ordering::Relaxed)
            )
        });
        bar.set_message(format!(
            "{files}{scans} scans, {:.1} scans/s",
            scans as f64 / secs
        ));
    };
    let result = std::thread::scope(|scope| {
        if !bar.is_hidden() {
            scope.spawn(|| {
                while !stop.load(Ordering::Relaxed) {
                    draw();
                    std::thread::sleep(std::time::Duration::from_millis(100));
                }
            });
        }
        let result = work();
        stop.store(true, Ordering::Relaxed);
        result
    });
    bar.finish_and_clear();
    result
}

/// Converts files with one set of settings; the decoder is loaded once and shared by
/// every file (and every thread).
pub(crate) struct FileConverter<'d> {
    decode_stage: Option<DecodeStage<'d>>,
    spatial_stage: Option<SpatialStage>,
    write_range: bool,
    channels: Vec<String>,
    opts: ConvertOptions,
    writer: WriterSettings,
    /// [`output_settings`].
    pub settings: String,
}

/// One converted file.
pub(crate) struct Converted {
    pub report: ConvertReport,
    pub seconds: f64,
}

impl<'d> FileConverter<'d> {
    pub fn new(
        args: &ConvertArgs,
        decoding: Option<&'d Decoding>,
        counters: &Counters,
    ) -> anyhow::Result<Self> {
        let settings = output_settings(args);
        let mut metadata = BTreeMap::from([
            ("tool".to_string(), "rangegan-mcap".to_string()),
            ("version".to_string(), env!("CARGO_PKG_VERSION").to_string()),
            ("args".to_string(), settings.clone()),
        ]);
        let (decode_stage, spatial_stage) = match decoding {
            Some(Decoding::Gan(decoder, outputs)) => {
                (Some(DecodeStage::new(decoder, outputs)?), None)
            }
            Some(Decoding::Spatial(model, outputs)) => {
                (None, Some(SpatialStage::new((**model).clone(), outputs)?))
            }
            None => (None, None),
        };
        let known: Vec<String> = std::iter::once("range".to_string())
            .chain(decode_stage.iter().flat_map(|s| s.channel_names()))
            .chain(spatial_stage.iter().flat_map(|s| s.channel_names()))
            // Without a model there is no decoded scene to write.
            .filter(|c| !(args.decode.prior_free && c == "x_d"))
            .collect();
        // Upsampled grids are named by their size, which follows each sensor's grid.
        let upsampled = |c: &str| {
            let size = c
                .strip_prefix("depth_")
                .or_else(|| c.strip_prefix("points_"));
            let dims = size.and_then(|s| s.split_once('x'));
            !args.decode.upsample.is_empty()
                && dims
                    .is_some_and(|(h, w)| h.parse::<usize>().is_ok() && w.parse::<usize>().is_ok())
        };
        let unknown = (args.channels.iter()).find(|c| !known.contains(c) && !upsampled(c));
        if let Some(unknown) = unknown {
            bail!(
                "--channels {unknown}: this conversion writes {}{}",
                known.join(", "),
                if decoding.is_none() {
                    " (decoded channels need --quality fast or paper)"
                } else {
                    ""
                }
            );
        }
        if let Some(Decoding::Spatial(..)) = decoding {
            metadata.insert(
                "decode_model".to_string(),
                decoding.map(Decoding::source).unwrap_or_default(),
            );
        }
        if let (Some(Decoding::Gan(decoder, _)), Some(_)) = (decoding, &decode_stage) {
            // What made the decoded channels, so a regenerated dataset says which weights it used.
            let schedule = &decoder.options().schedule;
            metadata.extend([
                ("decode_model".to_string(), decoder.source()),
                ("decode_steps".to_string(), schedule.describe()),
                (
                    "raydrop_calibration".to_string(),
                    match (decoder.calibration_source(), args.decode.raw_raydrop) {
                        (_, true) => "none".to_string(),
                        (Some(source), false) => source.to_string(),
                        (None, false) => {
                            "none: raydrop_prob is each recording's own drop rates".to_string()
                        }
                    },
                ),
            ]);
        }
        Ok(FileConverter {
            decode_stage,
            spatial_stage,
            write_range: channel_selected(&args.channels, "range"),
            channels: args.channels.clone(),
            opts: ConvertOptions {
                topics: (!args.topic.is_empty()).then(|| args.topic.clone()),
                sensor: sensor_choice(&args.sensor)?,
                columns: args.columns,
                strategy: args.projection,
                on_error: args.on_error,
                metadata,
                scans_processed: Some(counters.scans.clone()),
                prior: decoding.and_then(|d| decoding::prior_use(&args.decode, d)),
                model_sensor: match decoding {
                    Some(Decoding::Gan(decoder, _)) => decoder.model_sensor().clone(),
                    _ => crate::model::config::default_sensor(),
                },
                chain_stride: args.decode.chain_stride,
                check_every_fill: matches!(decoding, Some(Decoding::Spatial(..))),
                ..ConvertOptions::default()
            },
            writer: writer_settings(args)?,
            settings,
        })
    }

    /// Converts `input` into `output` (atomically; an existing `output` only with
    /// `overwrite`). `name` is the input's name in the output's metadata: its relative
    /// path in a dataset, so outputs do not depend on where the dataset is mounted.
    pub fn convert(
        &self,
        input: &Path,
        name: &str,
        output: &Path,
        overwrite: bool,
        counters: &Counters,
    ) -> anyhow::Result<Converted> {
        let started = std::time::Instant::now();
        let file = std::fs::File::open(input)
            .with_context(|| format!("cannot open {}", input.display()))?;
        let len = file.metadata().ok().map(|m| m.len());
        let mut opts = self.opts.clone();
        opts.metadata.insert("input".into(), name.into());
        let out = McapOutput::create_with(output, overwrite, self.writer)?;
        let range = |i: &pipeline::ScanInput<'_>| {
            if self.write_range {
                pipeline::range_stage(i)
            } else {
                Ok(Staged::Done(Vec::new()))
            }
        };
        // Which chosen channels some scan wrote: a chosen one that none wrote is reported.
        let written = std::sync::Mutex::new(std::collections::BTreeSet::new());
        let selected = |mut outputs: Vec<StageOutput>| {
            outputs.retain(|o| channel_selected(&self.channels, &o.suffix));
            if let Ok(mut w) = written.lock() {
                w.extend(outputs.iter().map(|o| o.suffix.clone()));
            }
            outputs
        };
        let decode = |i: &pipeline::ScanInput<'_>| {
            let staged = match (&self.decode_stage, &self.spatial_stage) {
                (Some(s), _) => s.run(i)?,
                (None, Some(s)) => s.run(i)?,
                (None, None) => return Ok(Staged::Done(Vec::new())),
            };
            Ok(match staged {
                Staged::Done(outputs) => Staged::Done(selected(outputs)),
                Staged::Later(later) => Staged::Later(Box::new(move || later().map(selected))),
            })
        };
        let stages: [&pipeline::Stage<'_>; 2] = [&range, &decode];
        let reader = std::io::BufReader::with_capacity(1 << 20, file);
        let mut last = 0;
        let result = pipeline::convert(input, reader, len, out, &opts, &stages, |p| {
            counters
                .bytes
                .fetch_add(p.bytes_read.saturating_sub(last), Ordering::Relaxed);
            last = last.max(p.bytes_read);
        });
        // A file that stopped early still counts as read, for the bar's total.
        let rest = len.unwrap_or(last).saturating_sub(last);
        counters.bytes.fetch_add(rest, Ordering::Relaxed);
        counters.files_done.fetch_add(1, Ordering::Relaxed);
        let mut report = result?;
        let written = written.into_inner().unwrap_or_default();
        report
            .warnings
            .extend(self.unwritten_channels(name, &written));
        Ok(Converted {
            report,
            seconds: started.elapsed().as_secs_f64(),
        })
    }

    /// A warning for each channel `--channels` chose that no scan of the file wrote (an
    /// upsampled grid whose size no topic's grid gives, say).
    fn unwritten_channels(
        &self,
        name: &str,
        written: &std::collections::BTreeSet<String>,
    ) -> Vec<pipeline::Warning> {
        let grids: Vec<&str> = written
            .iter()
            .filter_map(|s| s.strip_prefix("depth_"))
            .collect();
        self.channels
            .iter()
            .filter(|c| *c != "range")
            .filter(|c| !written.iter().any(|s| channel_selected(std::slice::from_ref(c), s)))
            .map(|c| pipeline::Warning {
                topic: String::new(),
                log_time_nanos: 0,
                message: format!(
                    "{name}: --channels {c} was not written: no scan gave it (the extra grids written: {})",
                    if grids.is_empty() {
                        "none".to_string()
                    } else {
                        grids.join(", ")
                    }
                ),
            })
            .collect()
    }
}

/// Input records a conversion copied.
fn records_copied(report: &ConvertReport) -> u64 {
    let c = &report.copied;
    c.messages + c.schemas + c.channels + c.attachments + c.metadata
}

fn total_scans(report: &ConvertReport) -> u64 {
    report.topics.values().map(|t| t.scans).sum()
}

fn total_malformed(report: &ConvertReport) -> u64 {
    report.topics.values().map(|t| t.malformed).sum()
}

/// Warnings a conversion reported (per message, per skipped chunk, a truncated end, orphans).
fn warning_count(report: &ConvertReport) -> u64 {
    report.warnings.len() as u64
        + report.model_fit.len() as u64
        + report.read.bad_chunks.len() as u64
        + report.read.bad_records.len() as u64
        + u64::from(report.read.stopped.is_some())
        + u64::from(report.copied.orphan_messages > 0)
}

/// Whether anything was skipped or unreadable (what `--strict` turns into exit code 3).
pub(crate) fn data_skipped(report: &ConvertReport) -> bool {
    report.skipped_anything()
}

/// The manifest's counts of a converted file.
pub(crate) fn manifest_counts(c: &Converted) -> Counts {
    Counts {
        records_copied: records_copied(&c.report),
        scans: total_scans(&c.report),
        malformed: total_malformed(&c.report),
        warnings: warning_count(&c.report),
        seconds: c.seconds,
    }
}

/// Prints a file's warnings and its summary line on stderr.
pub(crate) fn print_file_summary(global: &GlobalArgs, input: &Path, output: &Path, c: &Converted) {
    let report = &c.report;
    if !global.quiet {
        for w in report.warnings.iter().chain(&report.model_fit) {
            eprintln!("warning: {}", w.message);
        }
    }
    super::warn_read_damage(input, &report.read);
    if report.records_in.messages == 0 {
        eprintln!(
            "warning: {}: no message could be read{}",
            input.display(),
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
            input.display(),
            report.read.unread_bytes
        );
    }
    if report.copied.orphan_messages > 0 {
        eprintln!(
            "warning: {}: {} messages on channels that were never defined were dropped",
            input.display(),
            report.copied.orphan_messages
        );
    }
    if !global.quiet {
        let secs = c.seconds.max(1e-9);
        eprintln!(
            "{} -> {}: {} records copied, {} scans on {} topics -> {} new messages, {} malformed, {:.1} MB/s, {:.1} scans/s",
            input.display(),
            output.display(),
            records_copied(report),
            total_scans(report),
            report.topics.len(),
            report.outputs_written,
            total_malformed(report),
            report.read.bytes_read as f64 / 1e6 / secs,
            total_scans(report) as f64 / secs,
        );
    }
}

/// One file to one file; [`super::convert_dataset`] takes the dataset form.
pub fn run(global: &GlobalArgs, args: ConvertArgs) -> anyhow::Result<Outcome> {
    args.dataset.refuse_in_one_file_form()?;
    let input = &args.inputs[0];
    // Every file the conversion reads is an input: the recording, model, encoder and a
    // sensor profile given as a file.
    let sensor_file = Some(Path::new(&args.sensor)).filter(|p| p.is_file());
    let inputs: Vec<&Path> = std::iter::once(input.as_path())
        .chain(args.decode.model.as_deref())
        .chain(args.decode.encoder.as_deref())
        .chain(sensor_file)
        .collect();
    crate::io::writer::refuse_overwriting_inputs(&args.output, &inputs)?;
    if let Some(c) = args.columns {
        crate::lidar::profile::check_columns(c).map_err(anyhow::Error::msg)?;
    }
    std::fs::File::open(input).with_context(|| format!("cannot open {}", input.display()))?;
    let decoding = decoding::resolve(&args.decode, &args.channels)?;
    decoding::warn_uncalibrated(global, decoding.as_ref());
    let counters = Counters::default();
    let mut converter = FileConverter::new(&args, decoding.as_ref(), &counters)?;
    // One file: a --strict run that exits non-zero keeps no output.
    converter.opts.strict = args.strict;
    let size = std::fs::metadata(input).map(|m| m.len()).unwrap_or(0);
    let bar = super::progress_bar(global, size);
    let name = input.display().to_string();
    let converted = with_progress(&bar, &counters, None, || {
        converter.convert(input, &name, &args.output, args.force, &counters)
    })?;
    print_file_summary(global, input, &args.output, &converted);
    if global.json {
        // The manifest line of this file, so a driver running one file per task (e.g. on
        // Ray) can assemble a dataset's manifest.
        let mut entry = manifest::manifest_entry(
            &name,
            size,
            manifest::hash_file(input)?,
            &args.output.display().to_string(),
            &converter.settings,
            Ok(manifest_counts(&converted)),
        );
        manifest::finish_entry(&mut entry, &args.output)?;
        let summary = serde_json::json!({
            "input": input.display().to_string(),
            "output": args.output.display().to_string(),
            "seconds": converted.seconds,
            "report": converted.report,
            "manifest": entry,
        });
        println!("{}", serde_json::to_string_pretty(&summary)?);
    }
    Ok(if data_skipped(&converted.report) && args.strict {
        eprintln!(
            "{}: not written (--strict: input was skipped or unreadable)",
            args.output.display()
        );
        Outcome::DataSkipped
    } else {
        Outcome::Success
    })
}
