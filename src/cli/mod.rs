//! Command-line interface: clap types and glue. The only module that prints,
//! draws progress bars or maps results to exit codes; library code never sees
//! clap types (each subcommand resolves its arguments into library options).

mod calibrate;
mod convert;
mod convert_dataset;
mod decoding;
mod diagnose;
mod import;
mod info;
mod layout;
mod render;
mod sample;
mod segment;
mod simulate;
mod train;
mod train_encoder;
mod train_spatial;

use std::process::ExitCode;

use clap::{Parser, Subcommand};

/// rangegan-mcap: LiDAR range images and a range-image GAN for MCAP recordings.
#[derive(Debug, Parser)]
#[command(name = "rangegan-mcap", version, about, propagate_version = true)]
pub struct Args {
    #[command(flatten)]
    pub global: GlobalArgs,
    #[command(subcommand)]
    pub command: Command,
}

/// Flags every subcommand takes.
#[derive(Debug, Clone, clap::Args)]
pub struct GlobalArgs {
    /// No progress bar and no summary line on stderr.
    #[arg(long, short, global = true)]
    pub quiet: bool,
    /// Print a machine-readable JSON summary on stdout.
    #[arg(long, global = true)]
    pub json: bool,
    /// Worker threads (default: one per core; at most 1024).
    #[arg(long, global = true,
          value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..=1024))]
    pub threads: Option<usize>,
}

#[derive(Debug, Subcommand)]
pub enum Command {
    /// Copy a recording and add range-image channels for its point-cloud topics.
    Convert(convert::ConvertArgs),
    /// Fit the per-beam calibration of the ray-drop probability x_n on decoded training scans.
    CalibrateRaydrop(calibrate::CalibrateArgs),
    /// Find the physics a simulated recording leaves out, compared with a real one; fit it and report.
    Diagnose(diagnose::DiagnoseArgs),
    /// Channels, schemas, message counts, point-cloud topics and their sensor layout.
    Info(info::InfoArgs),
    /// Write a Foxglove layout for the channels `convert` wrote into a recording.
    Layout(layout::LayoutArgs),
    /// Turn a folder of scans (KITTI / SemanticKITTI `.bin`, nuScenes `.pcd.bin`, `.pcd`) into an
    /// MCAP of ROS 2 PointCloud2 messages.
    Import(import::ImportArgs),
    /// Apply (fitted) physics or a baseline ray-drop model to a simulated recording.
    Render(render::RenderArgs),
    /// Simulate a LiDAR drive through a procedural street scene, with switchable sensor physics.
    Simulate(simulate::SimulateArgs),
    /// Train the range-image GAN on KITTI scans (resumes an existing run directory).
    Train(train::TrainArgs),
    /// Train the amortised encoder of `convert --quality fast` against the frozen generator.
    TrainEncoder(train_encoder::TrainEncoderArgs),
    /// Train the spatial-latent model (encoder and renderer) that decodes every sensor.
    TrainSpatial(train_spatial::TrainSpatialArgs),
    /// Draw scans from the trained GAN: depth, drop probability, mask, range, points.
    Sample(sample::SampleArgs),
    /// Sim2Real segmentation: train a range-image segmentation network on labelled recordings, score it on real ones.
    Segment(segment::SegmentArgs),
}

/// Where a recording that a command writes from scratch goes (`import`, `simulate`).
#[derive(Debug, Clone, clap::Args)]
pub struct CloudOutputArgs {
    /// Output MCAP.
    pub output: std::path::PathBuf,
    /// Topic of the point clouds.
    #[arg(long, default_value = "/velodyne_points")]
    pub topic: String,
    /// Frame id of the point clouds.
    #[arg(long, default_value = "velodyne")]
    pub frame_id: String,
    /// Log time of the first scan, seconds since 1970-01-01 UTC; scans follow at 10 Hz.
    /// Default: the scans' own time where the files carry one (a KITTI drive's
    /// `timestamps.txt`, nuScenes file names), else 2020-01-01 00:00:00 UTC; never the
    /// clock, so the same input gives the same bytes.
    #[arg(long)]
    pub start_secs: Option<f64>,
    /// Overwrite an existing OUT.
    #[arg(long)]
    pub force: bool,
}

/// Where `import` and `simulate` start when neither `--start-secs` nor the files give a time:
/// 2020-01-01 00:00:00 UTC (fixed, so outputs are the same bytes on every run).
pub const DEFAULT_START_SECS: f64 = 1_577_836_800.0;

impl CloudOutputArgs {
    /// The output file, created atomically (refused if it exists, unless `--force`).
    pub fn create(&self) -> anyhow::Result<crate::io::McapOutput> {
        crate::io::McapOutput::create(&self.output, self.force)
    }

    /// The first scan's log time in nanoseconds, for `scans` scans at 10 Hz: `--start-secs`,
    /// else `own` (the scans' own time), else [`DEFAULT_START_SECS`]. Refused unless every
    /// scan's header stamp fits ROS 2's `int32` seconds (and so the log times their u64
    /// nanoseconds), rather than wrapping.
    pub fn start_nanos(&self, scans: u64, own: Option<f64>) -> anyhow::Result<u64> {
        let start = self.start_secs.or(own).unwrap_or(DEFAULT_START_SECS);
        let last = start + scans.saturating_sub(1) as f64 * 0.1;
        anyhow::ensure!(
            start.is_finite() && start >= 0.0 && last <= i32::MAX as f64,
            "--start-secs must be between 0 and {} so that the last of {scans} scans at 10 Hz \
             has a header stamp ROS 2 can hold (int32 seconds, until 2038-01-19); got {}",
            (i32::MAX as f64 - scans.saturating_sub(1) as f64 * 0.1).floor(),
            start
        );
        Ok((start * 1e9).round() as u64)
    }
}

/// Warnings for every part of `input` that could not be read: skipped chunks and
/// records, and the reason reading stopped early.
pub(crate) fn warn_read_damage(input: &std::path::Path, read: &crate::io::ReadReport) {
    for c in &read.bad_chunks {
        eprintln!(
            "warning: {}: skipped {c} ({} messages lost)",
            input.display(),
            c.messages
        );
    }
    for r in &read.bad_records {
        eprintln!("warning: {}: skipped {r}", input.display());
    }
    for r in &read.from_summary {
        eprintln!(
            "warning: {}: {r} rebuilt from the summary section (its own record was lost)",
            input.display()
        );
    }
    for r in &read.repaired {
        eprintln!("warning: {}: {r}", input.display());
    }
}

/// How a command ended when it did not fail outright.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Outcome {
    /// Everything was processed.
    Success,
    /// Done, but some input was skipped or could not be read (exit code 3).
    DataSkipped,
    /// Some files of a dataset could not be converted; the others were (exit code 4).
    FilesFailed,
}

impl Outcome {
    pub fn exit_code(self) -> ExitCode {
        match self {
            Outcome::Success => ExitCode::SUCCESS,
            Outcome::DataSkipped => ExitCode::from(3),
            Outcome::FilesFailed => ExitCode::from(4),
        }
    }
}

/// An optimisation step count: 0 to 100 000 (the paper's schedule is 1 000).
pub(crate) fn steps() -> clap::builder::RangedU64ValueParser<usize> {
    clap::builder::RangedU64ValueParser::<usize>::new().range(0..=100_000)
}

/// A speed flag in m/s: a finite number from 0 to 100 (360 km/h).
pub(crate) fn parse_speed_mps(text: &str) -> Result<f64, String> {
    let v: f64 = text.parse().map_err(|e| format!("{text:?}: {e}"))?;
    if !(0.0..=100.0).contains(&v) {
        return Err(format!("{text}: give a speed from 0 to 100 m/s"));
    }
    Ok(v)
}

/// [`parse_speed_mps`] for an `f32` flag.
pub(crate) fn parse_speed_mps_f32(text: &str) -> Result<f32, String> {
    parse_speed_mps(text).map(|v| v as f32)
}

/// Runs the parsed command.
pub fn run(args: Args) -> anyhow::Result<Outcome> {
    if let Some(n) = args.global.threads {
        rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build_global()
            .map_err(|e| anyhow::anyhow!("--threads {n}: cannot start {n} worker threads: {e}"))?;
    }
    match args.command {
        Command::Convert(a) if convert_dataset::is_dataset(&a) => {
            convert_dataset::run(&args.global, &a)
        }
        Command::Convert(a) => convert::run(&args.global, a),
        Command::CalibrateRaydrop(a) => calibrate::run(&args.global, a),
        Command::Diagnose(a) => diagnose::run(&args.global, a),
        Command::Info(a) => info::run(&args.global, a),
        Command::Layout(a) => layout::run(&args.global, a),
        Command::Render(a) => render::run(&args.global, a),
        Command::Import(a) => import::run(&args.global, a),
        Command::Simulate(a) => simulate::run(&args.global, a),
        Command::Train(a) => train::run_train(&args.global, a),
        Command::TrainEncoder(a) => train_encoder::run_train_encoder(&args.global, a),
        Command::TrainSpatial(a) => train_spatial::run_train_spatial(&args.global, a),
        Command::Sample(a) => sample::run(&args.global, a),
        Command::Segment(a) => segment::run_segment(&args.global, a),
    }
}

/// A byte-progress bar on stderr; hidden when stderr is not a terminal or `quiet`.
pub(crate) fn progress_bar(global: &GlobalArgs, total: u64) -> indicatif::ProgressBar {
    if global.quiet {
        return indicatif::ProgressBar::hidden();
    }
    let bar = indicatif::ProgressBar::with_draw_target(
        Some(total),
        indicatif::ProgressDrawTarget::stderr(),
    );
    let style = indicatif::ProgressStyle::with_template(
        "{bar:30} {bytes}/{total_bytes} {binary_bytes_per_sec} {msg} ETA {eta}",
    )
    .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar());
    bar.set_style(style);
    bar
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn arguments_parse() {
        let a = Args::try_parse_from([
            "rangegan-mcap",
            "convert",
            "in.mcap",
            "out.mcap",
            "--topic",
            "/a",
            "--topic",
            "/b",
            "--json",
        ])
        .unwrap();
        assert!(a.global.json);
        let Command::Convert(c) = a.command else {
            panic!("not convert")
        };
        assert_eq!(c.topic, vec!["/a".to_string(), "/b".to_string()]);
        assert_eq!(c.inputs, vec![std::path::PathBuf::from("in.mcap")]);
        let Command::Convert(c) =
            Args::try_parse_from(["rangegan-mcap", "convert", "a", "b/", "c", "--jobs", "2"])
                .unwrap()
                .command
        else {
            panic!("not convert")
        };
        assert_eq!((c.inputs.len(), c.output.to_str()), (2, Some("c")));
        assert!(Args::try_parse_from(["rangegan-mcap", "convert", "in.mcap"]).is_err());
        assert!(
            Args::try_parse_from(["rangegan-mcap", "convert", "a", "b", "--on-error", "maybe"])
                .is_err()
        );
    }
}
