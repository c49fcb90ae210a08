//! A GAN training run's settings: [`TrainConfig`] (saved as `config.json` before training
//! starts, and loaded with defaults for fields added since), the options of one invocation
//! and the state saved with each checkpoint.

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{Context, Result};
use burn::config::Config;
use burn::tensor::Device;
use serde::{Deserialize, Serialize};

use crate::lidar::SensorProfile;
use crate::model::baseline::ConvGeneratorConfig;
use crate::model::data::RangeDataset;
use crate::model::discriminator::DiscriminatorConfig;
use crate::model::generator::GeneratorConfig;
use crate::model::measurement::MeasurementConfig;
use crate::model::{AnyGenerator, Arch, ModelConfig};
use crate::util::rng::Rng;

use super::growth::Stage;
use super::reconstruct::ReconstructionConfig;
use super::regularise::{DRegularisation, LecamAnchors};
use super::run_dir::Backend;
use super::scans::ScanSource;

/// Everything that defines a training run; saved as `config.json` before training starts.
#[derive(Config, Debug)]
pub struct TrainConfig {
    #[config(default = "Arch::Dusty2")]
    pub arch: Arch,
    #[config(default = "GeneratorConfig::cpu()")]
    pub generator: GeneratorConfig,
    /// Used by `dusty1` (2 output channels) and `vanilla` (1).
    #[config(default = "ConvGeneratorConfig::cpu(2)")]
    pub conv_generator: ConvGeneratorConfig,
    #[config(default = "DiscriminatorConfig::cpu()")]
    pub discriminator: DiscriminatorConfig,
    #[config(default = "MeasurementConfig::new()")]
    pub measurement: MeasurementConfig,
    /// The sensor of the training scans at their columns (set from the dataset when the run
    /// starts): the model grid and network units of the trained model.
    #[config(default = "crate::model::config::default_sensor()")]
    pub sensor: SensorProfile,
    #[config(default = 8)]
    pub batch_size: usize,
    /// Adam, paper values: lr 0.002, betas (0, 0.99).
    #[config(default = 0.002)]
    pub lr: f64,
    /// The generator's own learning rate where it differs from the discriminator's `lr`
    /// (two time-scale updates): a generator that moves as fast as a small discriminator
    /// erases every difference the discriminator finds within a step.
    pub g_lr: Option<f64>,
    /// The generator takes a step on every this many discriminator steps (one batch of
    /// real scans each): a slow discriminator gets the time to find differences.
    #[config(default = 1)]
    pub g_every: usize,
    #[config(default = 0.0)]
    pub beta1: f32,
    #[config(default = 0.99)]
    pub beta2: f32,
    /// Weight of the (finite-difference) R1 penalty at full resolution, paper gamma = 1; a
    /// coarse-to-fine stage scales it with its pixel count.
    #[config(default = 1.0)]
    pub r1_gamma: f32,
    /// Lazy regularisation: every this many D steps, weighted by the interval.
    #[config(default = 16)]
    pub r1_interval: usize,
    /// Step of the finite difference, network units per pixel.
    #[config(default = 0.01)]
    pub r1_fd_step: f32,
    /// Generator EMA half-life in images.
    #[config(default = 10000.0)]
    pub ema_half_life_images: f64,
    /// EMA ramp-up: the half-life is at most this fraction of the images seen (StyleGAN2-ADA),
    /// so the EMA model is not stuck near the initial weights early on.
    #[config(default = 0.05)]
    pub ema_rampup: f64,
    /// Adaptive augmentation target of E[sign(D(real))].
    #[config(default = 0.6)]
    pub ada_target: f32,
    #[config(default = 4)]
    pub ada_interval: usize,
    /// Images for p to move by 1.
    #[config(default = 100000.0)]
    pub ada_speed_images: f64,
    /// Early random pixel dropout: initial probability, decaying linearly to 0.
    #[config(default = 0.5)]
    pub pixel_drop_start: f32,
    #[config(default = 50000.0)]
    pub pixel_drop_images: f64,
    /// Random azimuth phase in generator training (subgrid training, dusty2 only).
    #[config(default = true)]
    pub subgrid: bool,
    /// Stop after this many real images shown to D.
    #[config(default = 2000000)]
    pub total_images: u64,
    /// PNG snapshot (and checkpoint) interval; ~10 minutes at the CPU size.
    #[config(default = 2000)]
    pub snapshot_every_images: u64,
    #[config(default = 300)]
    pub checkpoint_every_secs: u64,
    #[config(default = 10)]
    pub log_every_steps: u64,
    #[config(default = 2)]
    pub seed: u64,
    /// Train only the generator's ray-drop logit (the second output of every block's
    /// head); its depth, synthesis layers and mapping stay frozen. For fine-tuning the
    /// drop model of a pretrained generator on real drop masks without touching x_d.
    #[config(default = false)]
    pub drop_head_only: bool,
    /// Coarse-to-fine stages (dusty2 only), in order; after the last, every block renders
    /// the full grid. Empty: the full grid from the start.
    #[config(default = "vec![]")]
    pub stages: Vec<Stage>,
    /// After each growth, the fresh discriminator trains alone for this many images before
    /// the generator takes its gradients again.
    #[config(default = 2000)]
    pub d_warmup_images: u64,
    /// The discriminator of each coarse-to-fine stage, where it differs from
    /// `discriminator` (which also serves the full grid): entry i for stage i.
    #[config(default = "vec![]")]
    pub stage_discriminators: Vec<DiscriminatorConfig>,
    /// Reconstruction-assisted training (dusty2): an encoder in the generator's loop.
    #[config(default = "None")]
    pub reconstruction: Option<ReconstructionConfig>,
    /// Weight of the ray-drop anchor in the generator's step: the squared difference between
    /// the generated scans' expected drop rate per row (1 - sigmoid(keep logit), no sampling)
    /// and a real batch's. The straight-through mask gradient lets the generator answer a
    /// discriminator that asks for farther returns by dropping rays; this term does not.
    /// 0: off.
    #[config(default = 0.0)]
    pub drop_rate_weight: f32,
    /// The discriminator's regularisers for small data beside ADA (all off by default).
    #[config(default = "DRegularisation::new()")]
    pub regularisation: DRegularisation,
    /// Train at full resolution on windows of this many columns of the turn (dusty2): the
    /// generator renders only the window, at a random azimuth, and the discriminator sees
    /// real windows of the same columns with each column's azimuth. An image counted is
    /// then a window. None: whole turns.
    #[config(default = "None")]
    pub window: Option<usize>,
    /// On windows of the turn: every this many steps, one step renders whole turns for a
    /// discriminator of whole turns (its own, started from a whole-turn source's), which
    /// keeps judging the layout of the turn while the windows teach detail. A whole turn
    /// counts as one image, as a window does. None: windows only.
    #[config(default = "None")]
    pub whole_every: Option<usize>,
    /// Share of the discriminator's real scans drawn from simulated scans of the run's
    /// sensor (`RUN_DIR/sim.bin`) instead of the real ones: structure the few real scans
    /// hold little of (cars, poles, walls with sharp edges). 0: real scans only.
    #[config(default = 0.0)]
    pub sim_share: f32,
}

/// How to run training (not part of the saved config).
#[derive(Debug, Clone)]
pub struct TrainOptions {
    pub run_dir: PathBuf,
    /// Dataset cache file (built from `source` if missing).
    pub dataset_cache: PathBuf,
    /// The scans to build the cache from; `None`: the cache must exist.
    pub source: Option<ScanSource>,
    /// Used when the run directory has no config.json yet; otherwise the saved one wins.
    pub config: TrainConfig,
    pub backend: Backend,
    /// Overrides the (saved) total image budget, e.g. to extend a finished run.
    pub total_images: Option<u64>,
    /// Stop after this much wall time (checkpointing first).
    pub max_duration: Option<Duration>,
    pub progress: bool,
    /// Start a new run from these weights (fine-tuning): a training run (its checkpoint's
    /// G, EMA G and D) or a model directory (EMA G only; D starts fresh).
    pub init_from: Option<PathBuf>,
    /// Replaces the (saved) discriminator regularisers, e.g. to branch a run into a
    /// comparison of them from one checkpoint.
    pub regularisation: Option<DRegularisation>,
    /// Replaces the (saved) share of simulated scans among the real ones, as
    /// `regularisation` does.
    pub sim_share: Option<f32>,
}

/// Mutable training state saved with each checkpoint.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct TrainState {
    pub step: u64,
    pub images: u64,
    pub ada_p: f32,
    pub rng: Rng,
    /// Sum of sign(D(real)) over the current ADA interval.
    pub ada_acc: f32,
    pub ada_count: u64,
    /// The coarse-to-fine stage the discriminator in the checkpoint belongs to.
    #[serde(default)]
    pub stage: usize,
    /// Images seen when that stage began.
    #[serde(default)]
    pub stage_start_images: u64,
    /// The LeCam term's moving averages of D's logits (from its first step).
    #[serde(default)]
    pub lecam: Option<LecamAnchors>,
    /// APA's probability of showing a generated image as real.
    #[serde(default)]
    pub apa_p: f32,
    /// The discriminator started fresh beside a trained generator (a fine-tuning run whose
    /// source's discriminator has another shape): it trains alone first, as after a growth.
    #[serde(default)]
    pub fresh_discriminator: bool,
}

/// Build the generator of `config.arch`.
pub fn init_generator(config: &TrainConfig, device: &Device) -> AnyGenerator {
    config.model().init_generator(device)
}

/// Load the EMA generator of a run (inference); returns it with the run's config.
pub fn load_generator(run_dir: &Path, device: &Device) -> Result<(AnyGenerator, TrainConfig)> {
    let m = crate::model::weights::Model::from_dir(run_dir, device)?;
    Ok((m.generator, load_config(&run_dir.join("config.json"))?))
}

/// Read a run's `config.json`; fields added to [`TrainConfig`] after the run started take
/// their defaults (burn's `Config::load` rejects missing fields), so old runs stay resumable.
pub fn load_config(path: &Path) -> Result<TrainConfig> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("failed to read '{}'", path.display()))?;
    parse_config(&text).with_context(|| format!("bad config '{}'", path.display()))
}

/// [`load_config`] on text.
pub fn parse_config(text: &str) -> Result<TrainConfig> {
    let mut saved: serde_json::Value = serde_json::from_str(text).context("not JSON")?;
    // Each per-stage discriminator takes the defaults of fields it predates, like the main one.
    if let Some(stages) = saved
        .get_mut("stage_discriminators")
        .and_then(|v| v.as_array_mut())
    {
        for d in stages {
            let mut merged = serde_json::to_value(DiscriminatorConfig::new())?;
            crate::util::json::merge(&mut merged, d.take());
            *d = merged;
        }
    }
    let mut merged = serde_json::to_value(TrainConfig::new())?;
    crate::util::json::merge(&mut merged, saved);
    let config: TrainConfig = serde_json::from_value(merged)?;
    config.check()?;
    Ok(config)
}

impl TrainConfig {
    /// Refuses settings that cannot train: sizes that cannot be built or would not fit in
    /// memory, an empty batch, rates that are not positive numbers. Every command that reads
    /// a run's `config.json` checks it here, before anything is sized by it.
    pub fn check(&self) -> Result<()> {
        use crate::util::bounds;
        self.model().check()?;
        self.discriminator.check()?;
        for d in &self.stage_discriminators {
            d.check()?;
        }
        bounds::size("batch_size", self.batch_size, 1..=4096)?;
        bounds::size("g_every", self.g_every, 1..=1024)?;
        bounds::size("r1_interval", self.r1_interval, 1..=1_000_000)?;
        bounds::size("ada_interval", self.ada_interval, 1..=1_000_000)?;
        let positive = |what: &str, v: f64| {
            anyhow::ensure!(
                v.is_finite() && v > 0.0,
                "{what} must be a positive number (got {v})"
            );
            Ok(())
        };
        positive("lr", self.lr)?;
        if let Some(g_lr) = self.g_lr {
            positive("g_lr", g_lr)?;
        }
        anyhow::ensure!(
            (0.0..=1.0).contains(&self.sim_share),
            "sim_share must be between 0 and 1 (got {})",
            self.sim_share
        );
        if self.window.is_some() {
            anyhow::ensure!(
                self.arch == Arch::Dusty2,
                "windows of the turn need the implicit generator (dusty2)"
            );
            anyhow::ensure!(
                self.reconstruction.is_none(),
                "windows of the turn train without the in-loop encoder, which reads whole turns: turn reconstruction off (--reconstruction 0)"
            );
        }
        if let Some(every) = self.whole_every {
            anyhow::ensure!(
                self.window.is_some() && every >= 2,
                "whole-turn steps (every {every}) go between steps on windows of the turn: they need a window and at least 2 steps apart"
            );
            anyhow::ensure!(
                self.regularisation.self_supervised <= 0.0,
                "whole-turn steps do not yet carry a self-supervised decoder of whole turns: leave --self-supervised off"
            );
        }
        Ok(())
    }

    /// The generator this run trains, as its model folder's config describes it.
    pub fn model(&self) -> ModelConfig {
        ModelConfig {
            arch: self.arch,
            generator: self.generator.clone(),
            conv_generator: self.conv_generator.clone(),
            measurement: self.measurement.clone(),
            sensor: self.sensor.clone(),
        }
    }

    /// Refuses a dataset this run cannot train on: another grid than the run's sensor's, or
    /// one that its networks cannot halve down to their coarsest level.
    pub fn check_grid(&self, data: &RangeDataset) -> Result<()> {
        let (h, w) = (data.height, data.width);
        anyhow::ensure!(
            self.sensor.beams() == h && self.sensor.columns == w,
            "the dataset's grid ({} beams x {w} columns, {}) is not this run's sensor's ({} x {}, {}): a run trains on one sensor's grid",
            h,
            data.profile.name,
            self.sensor.beams(),
            self.sensor.columns,
            self.sensor.name
        );
        let step = match self.arch {
            Arch::Dusty2 => self.generator.resolution_step(),
            _ => {
                let c = &self.conv_generator;
                let (gh, gw) = c.output_size();
                anyhow::ensure!(
                    (gh, gw) == (h, w),
                    "a {:?} generator renders {gh} x {gw} images; the dataset is {h} x {w} (use dusty2 for other grids)",
                    self.arch
                );
                1
            }
        };
        let d = &self.discriminator;
        let fold = step.max(d.stem.max(1) << d.channels.len().saturating_sub(1));
        anyhow::ensure!(
            h.is_multiple_of(fold) && w.is_multiple_of(fold),
            "the dataset's grid ({h} beams x {w} columns, {}) must divide by {fold} for these networks: choose --columns as a multiple of {fold}, and a sensor whose beams are",
            data.profile.name
        );
        if let Some(window) = self.window {
            // The strip rendered around a window (2 coarsest columns a side) fits in the turn.
            let strip = window + 4 * step;
            anyhow::ensure!(
                window > 0 && window.is_multiple_of(fold) && strip <= w,
                "a window of {window} columns must be a multiple of {fold} and, with {} columns of margin, fit the turn's {w}",
                4 * step
            );
        }
        Ok(())
    }

    /// The discriminator configuration of coarse-to-fine stage `stage`.
    pub fn discriminator_of(&self, stage: usize) -> &DiscriminatorConfig {
        self.stage_discriminators
            .get(stage)
            .filter(|_| stage < self.stages.len())
            .unwrap_or(&self.discriminator)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn old_configs_load_with_new_fields_defaulted() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("config.json");
        let config = TrainConfig::new()
            .with_batch_size(3)
            .with_stage_discriminators(vec![DiscriminatorConfig::cpu()]);
        let mut v = serde_json::to_value(config).expect("json");
        let obj = v.as_object_mut().expect("object");
        obj.remove("ema_rampup");
        obj.get_mut("generator")
            .and_then(|g| g.as_object_mut())
            .map(|g| g.remove("output_gain"));
        obj.get_mut("stage_discriminators")
            .and_then(|d| d[0].as_object_mut())
            .map(|d| d.remove("input_blur"));
        std::fs::write(&path, v.to_string()).expect("write");
        assert!(
            TrainConfig::load(&path).is_err(),
            "burn's loader needs every field"
        );
        let c = load_config(&path).expect("load");
        assert_eq!(c.batch_size, 3);
        assert_eq!(c.ema_rampup, 0.05);
        assert_eq!(c.generator.output_gain, 0.25);
        assert!(c.stage_discriminators[0].input_blur);
        assert_eq!(
            c.stage_discriminators[0].channels,
            DiscriminatorConfig::cpu().channels
        );
    }
}
