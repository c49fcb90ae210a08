//! `rangegan-mcap train-encoder RUN_DIR`: train the amortised encoder of `convert --quality
//! fast` against the frozen generator, on generated scans and the KITTI training scans; an
//! existing run directory resumes from its checkpoint.

use std::path::PathBuf;

use super::{GlobalArgs, Outcome};
use crate::train::encoder::{EncoderTrainConfig, EncoderTrainOptions, run};

#[derive(Debug, clap::Args)]
pub struct TrainEncoderArgs {
    #[command(flatten)]
    pub run: super::train::RunArgs,
    /// Generator to train against: a model or GAN run directory (default: the shipped one).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Stop after this many steps (also extends a resumed run).
    #[arg(long)]
    pub total_steps: Option<u64>,
}

pub fn run_train_encoder(_global: &GlobalArgs, args: TrainEncoderArgs) -> anyhow::Result<Outcome> {
    crate::train::Backend::from(args.run.backend).device()?;
    let mut config = EncoderTrainConfig::new();
    if let Some(s) = args.run.seed {
        config = config.with_seed(s);
    }
    let opts = EncoderTrainOptions {
        dataset_cache: args.run.cache_path(),
        max_duration: args.run.max_duration(),
        scans: args.run.training_files()?,
        run_dir: args.run.run_dir,
        model: args.model,
        config,
        total_steps: args.total_steps,
        backend: args.run.backend.into(),
    };
    run(&opts)?;
    Ok(Outcome::Success)
}
