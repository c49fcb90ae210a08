//! `rangegan-mcap train-encoder RUN_DIR`: train the amortised encoder of `convert --quality
//! fast` against the frozen generator, on generated scans and real scans of the generator's
//! sensor (projected onto its grid); an existing run directory resumes from its checkpoint.

use std::path::PathBuf;

use super::{GlobalArgs, Outcome};
use crate::lidar::SensorProfile;
use crate::model::ModelConfig;
use crate::model::weights::SHIPPED_CONFIG;
use crate::train::encoder::{EncoderTrainConfig, EncoderTrainOptions, run};
use crate::train::scans::Layout;

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
    let model = match &args.model {
        Some(dir) => ModelConfig::load(&dir.join("config.json"))?,
        None => ModelConfig::parse(SHIPPED_CONFIG)?,
    };
    let mut source = args.run.source()?;
    if let Some(source) = &mut source {
        on_model_grid(&mut source.layout, &model.sensor)?;
    }
    let mut config = EncoderTrainConfig::new();
    if let Some(s) = args.run.seed {
        config = config.with_seed(s);
    }
    let opts = EncoderTrainOptions {
        dataset_cache: args.run.cache_path(),
        max_duration: args.run.max_duration(),
        source,
        run_dir: args.run.run_dir,
        model: args.model,
        config,
        total_steps: args.total_steps,
        backend: args.run.backend.into(),
    };
    run(&opts)?;
    Ok(Outcome::Success)
}

/// The encoder reads the generator's grid: recordings are projected onto its sensor at its
/// columns, and a `--sensor` or `--columns` that says otherwise is refused.
fn on_model_grid(layout: &mut Layout, sensor: &SensorProfile) -> anyhow::Result<()> {
    if let Some(given) = &layout.sensor {
        anyhow::ensure!(
            given.elevation_deg == sensor.elevation_deg,
            "--sensor {} is not the generator's sensor ({}): an encoder reads its generator's grid",
            given.name,
            sensor.name
        );
    }
    if let Some(c) = layout.columns {
        anyhow::ensure!(
            c == sensor.columns,
            "--columns {c} is not the generator's {} columns",
            sensor.columns
        );
    }
    layout.sensor = Some(sensor.clone());
    layout.columns = Some(sensor.columns);
    Ok(())
}
