//! `rangegan-mcap segment train|eval|picture`: the Sim2Real segmentation benchmark. Train a
//! range-image segmentation network on labelled recordings (simulated, rendered or real),
//! score it on labelled real scans, and draw its predictions beside the ground truth.

use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;

use super::{GlobalArgs, Outcome};
use crate::segment::SegModel;
use crate::segment::data::{SegDataset, benchmark_profile};
use crate::segment::eval::{EvalReport, evaluate, picture};
use crate::segment::net::SegNetConfig;
use crate::segment::train::{SegTrainConfig, SegTrainOptions, run};

#[derive(Debug, clap::Args)]
pub struct SegmentArgs {
    #[command(subcommand)]
    pub command: SegmentCommand,
}

#[derive(Debug, clap::Subcommand)]
pub enum SegmentCommand {
    /// Train (or resume) a segmentation network on labelled recordings.
    Train(TrainArgs),
    /// Precision, recall and IoU per class and mean IoU on labelled recordings.
    Eval(EvalArgs),
    /// A PNG of one scan: range, ground truth and each model's prediction.
    Picture(PictureArgs),
}

#[derive(Debug, clap::Args)]
pub struct TrainArgs {
    /// Run directory (created; an existing one resumes from its checkpoint). The trained
    /// model is exported to RUN_DIR/model.
    pub run_dir: PathBuf,
    /// Training recordings (files or folders of .mcap) whose clouds carry a `label` field.
    #[arg(required = true)]
    pub recordings: Vec<PathBuf>,
    /// Point-cloud topic (default: each recording's first).
    #[arg(long)]
    pub topic: Option<String>,
    /// Optimiser steps of the whole run (saved with a new run).
    #[arg(long, default_value_t = 2000)]
    pub steps: u64,
    /// Random seed of the initial weights and the batches (saved with a new run).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Scans per step (saved with a new run; 1 to 1024).
    #[arg(long, default_value_t = 8,
          value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..=1024))]
    pub batch_size: usize,
    /// Stop after this many minutes with a checkpoint; run again to resume.
    #[arg(long)]
    pub minutes: Option<f64>,
    /// Held-out labelled recordings (files or folders of .mcap): the run is validated on them,
    /// exports its best network and stops when validation stops improving.
    #[arg(long = "val")]
    pub validation: Vec<PathBuf>,
    /// Validations without improvement before stopping (0: run the whole budget).
    #[arg(long, default_value_t = 6)]
    pub patience: u64,
    /// Steps between validations.
    #[arg(long, default_value_t = 200)]
    pub val_every: u64,
    /// Scale and random ray-drop augmentation, for small real training sets.
    #[arg(long)]
    pub augment: bool,
    /// Share of crops centred on a class drawn uniformly among those present.
    #[arg(long, default_value_t = 0.5)]
    pub balanced_crops: f32,
    /// Weight of the Lovász-softmax loss beside the cross-entropy (0: cross-entropy only).
    #[arg(long, default_value_t = 1.0)]
    pub lovasz: f64,
    /// Channels of the network's levels, comma-separated (default 16,32,48,64).
    #[arg(long, value_delimiter = ',')]
    pub widths: Option<Vec<usize>>,
}

#[derive(Debug, clap::Args)]
pub struct EvalArgs {
    /// Model folder (`segment.json` + `net.bpk`; a training run's `model/`).
    #[arg(long)]
    pub model: PathBuf,
    /// Labelled recordings (files or folders of .mcap), e.g. from `import` of a
    /// SemanticKITTI sequence.
    #[arg(required = true)]
    pub recordings: Vec<PathBuf>,
    /// Point-cloud topic (default: each recording's first).
    #[arg(long)]
    pub topic: Option<String>,
}

#[derive(Debug, clap::Args)]
pub struct PictureArgs {
    /// Model folders, one prediction row each (captioned with the folder's parent name when
    /// the folder is a run's `model/`, else its own name).
    #[arg(long = "model", required = true)]
    pub models: Vec<PathBuf>,
    /// Labelled recording.
    pub recording: PathBuf,
    /// Output PNG.
    pub output: PathBuf,
    /// Scan index within the recording.
    #[arg(long, default_value_t = 0)]
    pub scan: usize,
    /// Point-cloud topic (default: the recording's first).
    #[arg(long)]
    pub topic: Option<String>,
    /// Overwrite an existing OUTPUT.
    #[arg(long)]
    pub force: bool,
}

pub fn run_segment(global: &GlobalArgs, args: SegmentArgs) -> anyhow::Result<Outcome> {
    match args.command {
        SegmentCommand::Train(a) => train(global, a),
        SegmentCommand::Eval(a) => eval(global, a),
        SegmentCommand::Picture(a) => draw(a),
    }
}

fn expand(paths: &[PathBuf]) -> anyhow::Result<Vec<PathBuf>> {
    let mut out = Vec::new();
    for p in paths {
        // One input at a time: two folders may both hold a scene1.mcap.
        let found = crate::dataset::list(std::slice::from_ref(p), &[])?;
        anyhow::ensure!(!found.is_empty(), "{}: no .mcap recordings", p.display());
        out.extend(found.into_iter().map(|f| f.path));
    }
    Ok(out)
}

fn train(global: &GlobalArgs, a: TrainArgs) -> anyhow::Result<Outcome> {
    let max_duration = match a.minutes {
        Some(m) if m.is_finite() && m > 0.0 => Some(Duration::from_secs_f64(m * 60.0)),
        Some(m) => anyhow::bail!("--minutes must be > 0 (got {m})"),
        None => None,
    };
    let config = train_config(&a)?;
    let opts = SegTrainOptions {
        run_dir: a.run_dir,
        recordings: expand(&a.recordings)?,
        validation: expand(&a.validation)?,
        config,
        topic: a.topic,
        max_duration,
        progress: !global.quiet,
    };
    let summary = run(&opts)?;
    if global.json {
        println!("{}", serde_json::to_string(&summary)?);
    } else if !global.quiet {
        eprintln!(
            "{} of {} steps on {} scans in {:.0} s; model in {}{}",
            summary.steps,
            summary.total_steps,
            summary.scans,
            summary.seconds,
            summary.model_dir.display(),
            if summary.finished {
                ""
            } else {
                " (run again to resume)"
            }
        );
        if let Some(b) = &summary.best {
            eprintln!(
                "best validation mean IoU {:.1} % at step {}{}",
                100.0 * b.miou,
                b.step,
                if summary.flattened {
                    " (stopped: validation flattened)"
                } else {
                    ""
                }
            );
        }
    }
    Ok(Outcome::Success)
}

/// A new run's settings from the command line (a resumed run keeps its saved ones).
fn train_config(a: &TrainArgs) -> anyhow::Result<SegTrainConfig> {
    anyhow::ensure!(
        (0.0..=1.0).contains(&a.balanced_crops),
        "--balanced-crops must be within 0..1 (got {})",
        a.balanced_crops
    );
    anyhow::ensure!(
        a.lovasz.is_finite() && a.lovasz >= 0.0,
        "--lovasz must be >= 0 (got {})",
        a.lovasz
    );
    let mut net = SegNetConfig::new();
    if let Some(w) = &a.widths {
        net.widths = w.clone();
    }
    net.check()?;
    Ok(SegTrainConfig::new()
        .with_net(net)
        .with_total_steps(a.steps)
        .with_seed(a.seed)
        .with_batch_size(a.batch_size.max(1))
        .with_patience(a.patience)
        .with_validate_every_steps(a.val_every.max(1))
        .with_augment(a.augment)
        .with_balanced_crops(a.balanced_crops)
        .with_lovasz_weight(a.lovasz))
}

/// A model's name for tables and pictures: its folder, the run's for RUN/model, and the
/// config's with the seed for a shipped CONFIG/sSEED (`E/s0`).
fn model_name(dir: &std::path::Path) -> String {
    let dir = dir.canonicalize().unwrap_or_else(|_| dir.to_path_buf());
    let own = dir.file_name().map(|n| n.to_string_lossy().into_owned());
    let parent = || {
        (dir.parent().and_then(|p| p.file_name()))
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default()
    };
    let is_seed = |name: &str| {
        name.strip_prefix('s')
            .is_some_and(|n| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()))
    };
    match own.as_deref() {
        Some("model") => parent(),
        Some(name) if is_seed(name) => format!("{}/{name}", parent()),
        Some(name) => name.to_string(),
        None => dir.display().to_string(),
    }
}

fn eval(global: &GlobalArgs, a: EvalArgs) -> anyhow::Result<Outcome> {
    let device = burn::tensor::Device::flex();
    let model = SegModel::load(&a.model, &device)?;
    let data = SegDataset::from_recordings(
        &expand(&a.recordings)?,
        a.topic.as_deref(),
        &model.info.profile,
    )?;
    let report = evaluate(&model, &model_name(&a.model), &data, &device)?;
    if global.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print_report(&report);
    }
    Ok(Outcome::Success)
}

fn print_report(r: &EvalReport) {
    println!(
        "model {}: {} scans, {} labelled returns ({} in the frontal 90 degrees)",
        r.model, r.scans, r.scores.points, r.frontal.points
    );
    println!(
        "{:<11} {:>9} {:>9} {:>7} {:>7} {:>11}",
        "class", "points", "precision", "recall", "IoU", "frontal IoU"
    );
    for (c, f) in r.scores.classes.iter().zip(&r.frontal.classes) {
        println!(
            "{:<11} {:>9} {:>9} {:>7} {:>7} {:>11}",
            c.class,
            c.points,
            pct(c.precision),
            pct(c.recall),
            pct(c.iou),
            pct(f.iou)
        );
    }
    println!(
        "mIoU (named classes) {}   frontal {}",
        pct(r.scores.miou),
        pct(r.frontal.miou)
    );
    println!(
        "mIoU (car, person)   {}   frontal {}",
        pct(r.scores.miou_car_person),
        pct(r.frontal.miou_car_person)
    );
}

fn pct(v: Option<f64>) -> String {
    v.map_or("-".to_string(), |v| format!("{:.1}", 100.0 * v))
}

fn draw(a: PictureArgs) -> anyhow::Result<Outcome> {
    let mut inputs: Vec<&std::path::Path> = a.models.iter().map(|m| m.as_path()).collect();
    inputs.push(&a.recording);
    crate::io::writer::refuse_overwriting_inputs(&a.output, &inputs)?;
    anyhow::ensure!(
        a.force || !a.output.exists(),
        "{} exists; pass --force to replace it",
        a.output.display()
    );
    let device = burn::tensor::Device::flex();
    let models = a
        .models
        .iter()
        .map(|dir| Ok((model_name(dir), SegModel::load(dir, &device)?)))
        .collect::<anyhow::Result<Vec<_>>>()?;
    let profile = models
        .first()
        .map_or_else(benchmark_profile, |m| m.1.info.profile.clone());
    let data = SegDataset::from_recordings(
        std::slice::from_ref(&a.recording),
        a.topic.as_deref(),
        &profile,
    )?;
    picture(&models, &data, a.scan, &a.output)
        .with_context(|| format!("cannot draw {}", a.output.display()))?;
    Ok(Outcome::Success)
}

#[cfg(test)]
mod tests {
    use super::model_name;

    #[test]
    fn models_are_named_by_run_config_and_seed() {
        let dir = tempfile::tempdir().unwrap();
        for sub in ["E/s0", "runs/A-s1/model", "mine", "F/seed"] {
            std::fs::create_dir_all(dir.path().join(sub)).unwrap();
        }
        let name = |sub: &str| model_name(&dir.path().join(sub));
        assert_eq!(name("E/s0"), "E/s0");
        assert_eq!(name("runs/A-s1/model"), "A-s1");
        assert_eq!(name("mine"), "mine");
        assert_eq!(name("F/seed"), "seed");
    }
}
