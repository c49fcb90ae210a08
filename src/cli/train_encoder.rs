//! `rangegan-mcap train-encoder RUN_DIR`: train the amortised encoder of `convert --quality
//! fast` against the frozen generator, on generated scans and the KITTI training scans; an
//! existing run directory resumes from its checkpoint.

use std::path::PathBuf;
use std::time::Duration;

use super::{GlobalArgs, Outcome};
use crate::decode::encoder_train::{EncoderTrainConfig, EncoderTrainOptions, run};
use crate::model::data::kitti_training_files;

#[derive(Debug, clap::Args)]
pub struct TrainEncoderArgs {
    /// Run directory: config.json, checkpoint/, export/, log.jsonl. Resumes if it exists.
    pub run_dir: PathBuf,
    /// Folder holding kitti_raw_drive_a/ and semantickitti_mini/ (sequences 00, 07 held out).
    #[arg(long, default_value = "../shared/real_lidar")]
    pub data: PathBuf,
    /// Projected-dataset cache (default: RUN_DIR/dataset.bin).
    #[arg(long)]
    pub cache: Option<PathBuf>,
    /// Generator to train against: a model or GAN run directory (default: the shipped one).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Stop after this many steps (also extends a resumed run).
    #[arg(long)]
    pub total_steps: Option<u64>,
    /// Stop (with a checkpoint) after this many minutes.
    #[arg(long)]
    pub max_minutes: Option<f64>,
    /// Seed of a new run.
    #[arg(long)]
    pub seed: Option<u64>,
}

pub fn run_train_encoder(_global: &GlobalArgs, args: TrainEncoderArgs) -> anyhow::Result<Outcome> {
    let mut config = EncoderTrainConfig::new();
    if let Some(s) = args.seed {
        config = config.with_seed(s);
    }
    let opts = EncoderTrainOptions {
        dataset_cache: args
            .cache
            .clone()
            .unwrap_or_else(|| args.run_dir.join("dataset.bin")),
        run_dir: args.run_dir,
        scans: kitti_training_files(&args.data)?,
        model: args.model,
        config,
        total_steps: args.total_steps,
        max_duration: args.max_minutes.map(|m| Duration::from_secs_f64(m * 60.0)),
    };
    run(&opts)?;
    Ok(Outcome::Success)
}
