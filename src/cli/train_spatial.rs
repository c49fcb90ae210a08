//! `rangegan-mcap train-spatial RUN_DIR`: train the spatial-latent model (encoder and
//! renderer) on KITTI at two resolutions and simulated scans of every sensor family; an
//! existing run directory resumes from its checkpoint.

use std::path::PathBuf;

use super::{GlobalArgs, Outcome};
use crate::train::spatial::{SpatialTrainConfig, SpatialTrainOptions, run};

#[derive(Debug, clap::Args)]
pub struct TrainSpatialArgs {
    /// Run directory (created; resumed when it holds a checkpoint).
    pub run_dir: PathBuf,
    /// The `real_lidar` folder with `kitti_fullres_drive_c/` and the KITTI drives.
    #[arg(long, default_value = "../shared/real_lidar")]
    pub real_lidar: PathBuf,
    /// Stop after this many minutes (checkpointing first).
    #[arg(long)]
    pub max_minutes: Option<f64>,
    /// Stop after this many steps (also extends a resumed run).
    #[arg(long)]
    pub total_steps: Option<u64>,
    /// Seed of a new run.
    #[arg(long)]
    pub seed: Option<u64>,
    /// Simulated scans per sensor family of a new run.
    #[arg(long)]
    pub sim_per_sensor: Option<usize>,
    #[arg(long, value_enum, default_value = "flex")]
    pub backend: super::train::BackendArg,
}

pub fn run_train_spatial(_global: &GlobalArgs, args: TrainSpatialArgs) -> anyhow::Result<Outcome> {
    crate::train::Backend::from(args.backend).device()?;
    let mut config = SpatialTrainConfig::new();
    if let Some(s) = args.seed {
        config = config.with_seed(s);
    }
    if let Some(n) = args.sim_per_sensor {
        config = config.with_sim_per_sensor(n);
    }
    let opts = SpatialTrainOptions {
        run_dir: args.run_dir,
        real_lidar: args.real_lidar,
        config,
        total_steps: args.total_steps,
        max_duration: args
            .max_minutes
            .map(|m| std::time::Duration::from_secs_f64(m.max(0.0) * 60.0)),
        backend: args.backend.into(),
    };
    run(&opts)?;
    Ok(Outcome::Success)
}
