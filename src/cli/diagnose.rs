//! `rangegan-mcap diagnose --sim SIM.mcap --real REAL.mcap [--topic T] --report DIR`:
//! locates where a simulated and a real recording drop rays (or place returns)
//! differently, names the left-out physics, fits it on real scans and shows the
//! held-out fit improve. Writes DIR/report.json, report.html, fitted_physics.json
//! and PNG plots.

use std::path::PathBuf;

use anyhow::Context;
use rayon::prelude::*;

use super::{GlobalArgs, Outcome};
use crate::lidar::{RangeImage, SensorProfile};
use crate::physics::diagnose::{DiagnoseOptions, diagnose};
use crate::physics::diagnose_features::{FeatureOptions, ScanFeatures};
use crate::recording::{self, Grid};
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
    /// Output folder for report.json, report.html, fitted_physics.json and the plots.
    #[arg(long)]
    pub report: PathBuf,
    /// Sensor profile both are projected onto (default: the sim's `simulate`
    /// metadata, else estimated from its first scan).
    #[arg(long)]
    pub sensor: Option<String>,
    /// Range-image columns.
    #[arg(long, default_value_t = 512)]
    pub columns: usize,
    /// Most drop effects to add.
    #[arg(long, default_value_t = 3)]
    pub max_effects: usize,
    /// Real ego speed, m/s, to turn a seam shift into a motion-distortion scale
    /// (default: the real recording's `simulate` metadata, else unknown).
    #[arg(long)]
    pub real_speed_mps: Option<f64>,
}

fn features(images: &[RangeImage]) -> Vec<ScanFeatures> {
    images
        .par_iter()
        .map(|img| ScanFeatures::from_image(img, &FeatureOptions::default()))
        .collect()
}

pub fn run(global: &GlobalArgs, args: DiagnoseArgs) -> anyhow::Result<Outcome> {
    anyhow::ensure!(args.columns > 0, "--columns must be > 0");
    let grid = match &args.sensor {
        Some(s) => Grid::Fixed(
            SensorProfile::resolve(s)
                .with_context(|| format!("--sensor {s}"))?
                .with_columns(args.columns),
        ),
        None => Grid::FromRecording {
            columns: Some(args.columns),
        },
    };
    let sim = recording::read(&args.sim, args.topic.as_deref(), &grid)
        .with_context(|| format!("reading --sim {}", args.sim.display()))?;
    let real = recording::read(
        &args.real,
        args.topic.as_deref(),
        &Grid::Fixed(sim.profile.clone()),
    )
    .with_context(|| format!("reading --real {}", args.real.display()))?;
    anyhow::ensure!(
        real.images.len() >= 2,
        "{}: topic {} has {} readable scan(s); the diagnosis needs at least 2 (fit and held-out)",
        args.real.display(),
        real.topic,
        real.images.len()
    );
    let (f_sim, f_real) = (features(&sim.images), features(&real.images));
    let options = DiagnoseOptions {
        max_effects: args.max_effects,
        residual: crate::physics::diagnose_residual::ResidualContext {
            speed_mps: args.real_speed_mps.or(real.speed_mps()),
            period_s: 0.1,
        },
        ..DiagnoseOptions::default()
    };
    let diagnosis = diagnose(&f_sim, &f_real, &sim.physics(), "neighbour-fill", &options)
        .with_context(|| {
            format!(
                "diagnosing {} against {}",
                args.real.display(),
                args.sim.display()
            )
        })?;
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
            eprintln!("warning: {s}; scan skipped");
        }
    }
    let r = &diagnosis.report;
    if global.json {
        println!(
            "{}",
            serde_json::json!({"report": args.report, "effects": r.effects.iter().map(|e| &e.id).collect::<Vec<_>>(),
                "fit": r.fit, "files": files, "skipped_scans": skipped})
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
    Ok(if skipped > 0 {
        Outcome::DataSkipped
    } else {
        Outcome::Success
    })
}
