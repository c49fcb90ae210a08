//! `rangegan-mcap diagnose --sim SIM.mcap --real REAL.mcap [--topic T] --report DIR`
//! `[--force] [--sensor S] [--projection P] [--strict]`:
//! locates where a simulated and a real recording drop rays (or place returns)
//! differently, names the left-out physics, fits it on real scans and shows the
//! held-out fit improve. Writes DIR/report.json, report.html, fitted_physics.json
//! and PNG plots. Exit code 0 when the report was written (3 under `--strict` if
//! scans were skipped).

use std::path::PathBuf;

use anyhow::Context;

use super::{GlobalArgs, Outcome};
use crate::decode::amortised::TrainedEncoder;
use crate::decode::{DecodeOptions, Decoder, Quality, scan_seed};
use crate::diagnose::completion::{Completion, gan_features, neighbour_features};
use crate::diagnose::features::{FeatureOptions, ScanFeatures};
use crate::diagnose::report::{DiagnoseOptions, diagnose};
use crate::error::Location;
use crate::lidar::{SensorProfile, Strategy};
use crate::model::weights::Model;
use crate::recording::{self, Grid, Recording};
use crate::report;

#[derive(Debug, clap::Args)]
pub struct DiagnoseArgs {
    /// The simulated recording (the simulator's physics as given).
    #[arg(long)]
    pub sim: PathBuf,
    /// The real recording (unpaired: other scenes are fine).
    #[arg(long)]
    pub real: PathBuf,
    /// Point-cloud topic in both recordings (default: the first point-cloud topic of each).
    #[arg(long)]
    pub topic: Option<String>,
    /// Output folder for report.json, report.html, fitted_physics.json and the
    /// plots (refused if it exists, unless --force).
    #[arg(long)]
    pub report: PathBuf,
    /// Replace the files of an existing report folder.
    #[arg(long)]
    pub force: bool,
    /// Sensor profile both are projected onto: `auto` (the sim's `simulate`
    /// metadata, else estimated from its first scan), a built-in name (hdl64e,
    /// hdl32e, vlp16, vlp32c, vls128, pandar64, pandarxt32, os0-N, os1-N, os1-N-gen1, os2-N),
    /// or a profile / Ouster metadata JSON file.
    #[arg(long, default_value = "auto")]
    pub sensor: String,
    /// Range-image columns.
    #[arg(long, default_value_t = 512)]
    pub columns: usize,
    /// How a point's row is found (default: chosen from each recording's data).
    #[arg(long, value_enum, default_value = "auto")]
    pub projection: Strategy,
    /// Exit non-zero (3) when any scan was skipped (unreadable or not
    /// projectable); without it the exit code is 0 whenever the report was written.
    #[arg(long)]
    pub strict: bool,
    /// Most drop effects to add.
    #[arg(long, default_value_t = 3)]
    pub max_effects: usize,
    /// Real ego speed, m/s, to turn the motion measured at the seam into a motion-distortion
    /// scale (default: the real recording's `simulate` metadata, else the speed measured at
    /// the seam is the effect's).
    #[arg(long, value_parser = super::parse_speed_mps)]
    pub real_speed_mps: Option<f64>,
    /// How dropped pixels get their geometry before incidence and edges are
    /// computed: `gan` (the GAN's completed depth, auto-decoded for every scan)
    /// or `neighbour` (mean range of the nearest returns; the fallback per scan).
    #[arg(long, value_enum, default_value = "gan")]
    pub completion: CompletionArg,
    #[command(flatten)]
    pub gan: GanArgs,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum CompletionArg {
    Neighbour,
    Gan,
}

/// The GAN behind `diagnose --completion gan` and `render --raydrop gan`.
#[derive(Debug, clap::Args)]
pub struct GanArgs {
    /// Generator: a model directory or a training run directory (default: the
    /// shipped weights).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Encoder (default: the shipped weights).
    #[arg(long)]
    pub encoder: Option<PathBuf>,
    /// Pivotal-tuning steps per scan (`diagnose` default 0: the encoder's
    /// prediction alone, which keeps two 100-scan recordings under a minute;
    /// `render` default 33, `convert --quality fast`'s, ~0.8 s per scan per core).
    #[arg(long, value_parser = super::steps())]
    pub tune_steps: Option<usize>,
}

impl GanArgs {
    /// Whether any of the flags was given (they need the GAN mode of their command).
    pub(crate) fn given(&self) -> bool {
        self.model.is_some() || self.encoder.is_some() || self.tune_steps.is_some()
    }

    /// The `fast` decoder, with `default_tune_steps` unless `--tune-steps` says otherwise.
    pub(crate) fn decoder(&self, default_tune_steps: Option<usize>) -> anyhow::Result<Decoder> {
        let device = burn::tensor::Device::flex();
        let model = Model::load(self.model.as_deref(), &device)?;
        let mut opts = DecodeOptions::new(Quality::Fast);
        if let Some(n) = self.tune_steps.or(default_tune_steps) {
            opts.schedule.set_tune_steps(n);
        }
        let mut decoder = Decoder::new(model, opts)?;
        if let Some(dir) = &self.encoder {
            decoder = decoder.with_encoder(TrainedEncoder::from_dir(dir, &device)?)?;
        }
        Ok(decoder)
    }
}

/// Features of a recording's scans with the chosen completion; the number of
/// scans that fell back to the neighbour fill (warned on stderr).
fn features(
    global: &GlobalArgs,
    rec: &Recording,
    path: &std::path::Path,
    decoder: Option<&Decoder>,
) -> (Vec<ScanFeatures>, usize) {
    let options = FeatureOptions::default();
    let (mut features, fallbacks) = match decoder {
        None => (neighbour_features(&rec.images, &options), 0),
        Some(decoder) => {
            let seeds: Vec<u64> = rec
                .log_times
                .iter()
                .map(|t| scan_seed(&rec.topic, *t))
                .collect();
            let done = gan_features(decoder, &rec.images, &seeds, &options);
            if !global.quiet {
                for (i, why) in &done.fallbacks {
                    eprintln!(
                        "warning: {}: {why}; completed by neighbour fill",
                        Location::message(path, &rec.topic, rec.log_times[*i])
                    );
                }
            }
            (done.features, done.fallbacks.len())
        }
    };
    for (f, seam) in features.iter_mut().zip(&rec.seams) {
        f.seam = seam.clone();
    }
    (features, fallbacks)
}

/// Refuses a report folder where the report would replace one of the files the diagnosis
/// reads (`report.json`, `report.html`, `fitted_physics.json`, `*.png`), `--force` or not.
fn refuse_report_over_inputs(args: &DiagnoseArgs) -> anyhow::Result<()> {
    let sensor_file = Some(std::path::Path::new(&args.sensor)).filter(|p| p.is_file());
    let inputs = [args.sim.as_path(), args.real.as_path()]
        .into_iter()
        .chain(sensor_file);
    for input in inputs {
        let name = input.file_name().map(|n| n.to_string_lossy().into_owned());
        let written = name.as_deref().is_some_and(|n| {
            ["report.json", "report.html", "fitted_physics.json"].contains(&n)
                || n.ends_with(".png")
        });
        if written && crate::io::writer::lies_in(input, &args.report) {
            anyhow::bail!(
                "{}: the report would replace the input {}; choose another --report folder (inputs are never modified)",
                args.report.display(),
                input.display()
            );
        }
    }
    Ok(())
}

/// Refuses to compare recordings of sensors with different beam counts: projected on one
/// grid, the smaller one's rows would read as dropped beams, and the diagnosis would "find"
/// a dropout the sensors never had.
fn refuse_other_sensors(
    args: &DiagnoseArgs,
    sim: &recording::Recording,
    real: &recording::Recording,
) -> anyhow::Result<()> {
    let (Some(a), Some(b)) = (&sim.own_sensor, &real.own_sensor) else {
        return Ok(());
    };
    if recording::other_sensors(a, b) {
        let (na, nb) = (a.beams(), b.beams());
        anyhow::bail!(
            "--sim {} is a {na}-beam sensor ({}) and --real {} a {nb}-beam one ({}): a diagnosis compares two recordings of one sensor; simulate the real sensor (`rangegan-mcap simulate --sensor ...`) and diagnose again",
            args.sim.display(),
            a.name,
            args.real.display(),
            b.name
        );
    }
    Ok(())
}

pub fn run(global: &GlobalArgs, args: DiagnoseArgs) -> anyhow::Result<Outcome> {
    crate::lidar::profile::check_columns(args.columns).map_err(anyhow::Error::msg)?;
    refuse_report_over_inputs(&args)?;
    let occupied = args.report.exists()
        && std::fs::read_dir(&args.report).map_or(true, |mut d| d.next().is_some());
    if occupied && !args.force {
        anyhow::bail!(
            "{} exists; choose another --report folder or add --force to replace its files",
            args.report.display()
        );
    }
    let grid = match args.sensor.as_str() {
        "auto" => Grid::FromRecording {
            columns: Some(args.columns),
        },
        s => Grid::Fixed(
            SensorProfile::resolve(s)
                .with_context(|| format!("--sensor {s}"))?
                .with_columns(args.columns),
        ),
    };
    let sim = recording::read_with(&args.sim, args.topic.as_deref(), &grid, args.projection)
        .with_context(|| format!("reading --sim {}", args.sim.display()))?;
    let real = recording::read_with(
        &args.real,
        args.topic.as_deref(),
        &Grid::Fixed(sim.profile.clone()),
        args.projection,
    )
    .with_context(|| format!("reading --real {}", args.real.display()))?;
    refuse_other_sensors(&args, &sim, &real)?;
    let completion = match args.completion {
        CompletionArg::Neighbour => {
            anyhow::ensure!(
                !args.gan.given(),
                "--model, --encoder and --tune-steps are for --completion gan"
            );
            Completion::Neighbour
        }
        CompletionArg::Gan => Completion::Gan,
    };
    let decoder = match completion {
        Completion::Gan => Some(args.gan.decoder(Some(0)).context("--completion gan")?),
        Completion::Neighbour => None,
    };
    let started = std::time::Instant::now();
    let (f_sim, fell_sim) = features(global, &sim, &args.sim, decoder.as_ref());
    let (f_real, fell_real) = features(global, &real, &args.real, decoder.as_ref());
    let completion_s = started.elapsed().as_secs_f64();
    let options = DiagnoseOptions {
        max_effects: args.max_effects,
        residual: crate::diagnose::residual::ResidualContext {
            speed_mps: args.real_speed_mps.or(real.speed_mps()),
            period_s: 0.1,
            sweep: None,
        },
        ..DiagnoseOptions::default()
    };
    let mut diagnosis = diagnose(&f_sim, &f_real, &sim.physics(), completion.name(), &options)
        .with_context(|| {
            format!(
                "diagnosing {} against {}",
                args.real.display(),
                args.sim.display()
            )
        })?;
    diagnosis.report.inputs.completion_model = decoder.as_ref().map(|d| {
        format!(
            "{} (fast: {} pivotal-tuning steps per scan)",
            d.source(),
            d.options().schedule.tune_steps
        )
    });
    diagnosis.report.inputs.completion_fallback_scans = fell_sim + fell_real;
    let provenance = report::Provenance {
        sim: args.sim.display().to_string(),
        real: args.real.display().to_string(),
        topic_sim: sim.topic.clone(),
        topic_real: real.topic.clone(),
        sensor: format!(
            "{} ({}x{})",
            sim.profile.name,
            sim.profile.beams(),
            sim.profile.columns
        ),
    };
    let files = report::write(&args.report, &diagnosis, &provenance)?;
    let skipped = sim.skipped.len() + real.skipped.len();
    for s in sim.skipped.iter().chain(&real.skipped) {
        if !global.quiet {
            eprintln!(
                "warning: {s}; scan skipped (--sensor, --columns or --projection choose another grid)"
            );
        }
    }
    let r = &diagnosis.report;
    if r.inputs.scene.differs && !global.quiet {
        eprintln!("warning: {}", r.inputs.scene.sentence());
    }
    if r.inputs.held_out == "pixels" && !global.quiet {
        eprintln!("warning: {}", crate::diagnose::gaps::ONE_SCAN_CAVEAT);
    }
    if let Some(gaps) = crate::diagnose::gaps::summary(&r.inputs.gaps)
        && !global.quiet
    {
        eprintln!("warning: {gaps}");
    }
    if global.json {
        println!(
            "{}",
            serde_json::json!({"report": args.report.display().to_string(), "effects": r.effects.iter().map(|e| &e.id).collect::<Vec<_>>(),
                "fit": r.fit, "scene": r.inputs.scene, "files": files, "skipped_scans": skipped,
                "completion": completion.name(), "completion_seconds": completion_s})
        );
    } else if !global.quiet {
        eprintln!(
            "{}: {} sim vs {} real scans; effects: [{}]; held-out {} {:.5} -> {:.5}",
            args.report.join("report.html").display(),
            r.inputs.sim_scans,
            r.inputs.real_scans,
            r.effects
                .iter()
                .map(|e| format!("{} ({:.2})", e.id, e.confidence))
                .collect::<Vec<_>>()
                .join(", "),
            r.fit.metric,
            r.fit.before,
            r.fit.after
        );
    }
    Ok(if skipped > 0 && args.strict {
        Outcome::DataSkipped
    } else {
        Outcome::Success
    })
}
