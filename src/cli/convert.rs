//! `rangegan-mcap convert IN OUT`: copy every record, add range-image channels.

use std::collections::BTreeMap;
use std::path::PathBuf;

use anyhow::{Context, bail};

use super::{GlobalArgs, Outcome};
use crate::io::{McapOutput, OnError};
use crate::lidar::{SensorProfile, Strategy};
use crate::pipeline::{self, ConvertOptions, SensorChoice, Stage};

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
    pub projection: ProjectionArg,
    /// What to do with a corrupt chunk.
    #[arg(long, value_enum, default_value = "fail")]
    pub on_error: OnError,
    /// Exit non-zero (3) when anything was skipped or unreadable (truncated input,
    /// skipped chunks, undecodable point clouds).
    #[arg(long)]
    pub strict: bool,
    /// Overwrite an existing OUT.
    #[arg(long)]
    pub force: bool,
}

#[derive(Debug, Clone, Copy, clap::ValueEnum)]
pub enum ProjectionArg {
    Auto,
    RingField,
    RingOrder,
    ColumnMajor,
    RowMajor,
    Spherical,
}

impl From<ProjectionArg> for Strategy {
    fn from(p: ProjectionArg) -> Self {
        match p {
            ProjectionArg::Auto => Strategy::Auto,
            ProjectionArg::RingField => Strategy::RingField,
            ProjectionArg::RingOrder => Strategy::RingOrder,
            ProjectionArg::ColumnMajor => Strategy::ColumnMajor,
            ProjectionArg::RowMajor => Strategy::RowMajor,
            ProjectionArg::Spherical => Strategy::Spherical,
        }
    }
}

/// Resolves the sensor argument shared by several subcommands.
pub(crate) fn sensor_choice(sensor: &str) -> anyhow::Result<SensorChoice> {
    Ok(if sensor == "auto" {
        SensorChoice::Auto
    } else {
        SensorChoice::Fixed(SensorProfile::resolve(sensor)?)
    })
}

fn same_file(a: &std::path::Path, b: &std::path::Path) -> bool {
    match (a.canonicalize(), b.canonicalize()) {
        (Ok(a), Ok(b)) => a == b,
        _ => false,
    }
}

pub fn run(global: &GlobalArgs, args: ConvertArgs) -> anyhow::Result<Outcome> {
    if args.input == args.output || same_file(&args.input, &args.output) {
        bail!(
            "{}: output is the input; write to another file (inputs are never modified)",
            args.output.display()
        );
    }
    let file = std::fs::File::open(&args.input)
        .with_context(|| format!("cannot open {}", args.input.display()))?;
    let len = file.metadata().ok().map(|m| m.len());
    let metadata = BTreeMap::from([
        ("tool".to_string(), "rangegan-mcap".to_string()),
        ("version".to_string(), env!("CARGO_PKG_VERSION").to_string()),
        (
            "args".to_string(),
            std::env::args().skip(1).collect::<Vec<_>>().join(" "),
        ),
        ("input".to_string(), args.input.display().to_string()),
    ]);
    let opts = ConvertOptions {
        topics: (!args.topic.is_empty()).then(|| args.topic.clone()),
        sensor: sensor_choice(&args.sensor)?,
        columns: args.columns,
        strategy: args.projection.into(),
        on_error: args.on_error,
        metadata,
        ..ConvertOptions::default()
    };
    let out = McapOutput::create(&args.output, args.force)?;

    let bar = super::progress_bar(global, len.unwrap_or(0));
    let started = std::time::Instant::now();
    let stages: [&Stage<'_>; 1] = [&pipeline::range_stage];
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
    for c in &report.read.bad_chunks {
        eprintln!(
            "warning: {}: skipped {c} ({} messages lost)",
            args.input.display(),
            c.messages
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
    let skipped = malformed > 0
        || report.read.stopped.is_some()
        || !report.read.bad_chunks.is_empty()
        || report.copied.orphan_messages > 0;
    Ok(if skipped && args.strict {
        Outcome::DataSkipped
    } else {
        Outcome::Success
    })
}
