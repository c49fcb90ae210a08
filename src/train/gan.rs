//! The GAN training loop: non-saturating loss, a finite-difference R1 penalty (burn has no
//! double backward), Adam, generator EMA, adaptive augmentation restricted to operations that
//! keep the circular structure, early random pixel dropout, checkpoints with resume, a JSONL
//! loss log, an indicatif bar and PNG snapshots. Entry point: [`run`].
//!
//! Run directory layout: `config.json` (written first), `checkpoint/` (g, g_ema, d, optimiser
//! records, state.json; replaced atomically), `log.jsonl`, `snapshots/*.png`.

use std::fs::OpenOptions;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail, ensure};
use burn::config::Config;
use burn::module::{Module, ModuleMapper, ModuleVisitor, Param};
use burn::optim::{AdamConfig, GradientsParams, ModuleOptimizer};
use burn::tensor::activation::softplus;
use burn::tensor::{Device, Tensor};
use indicatif::{ProgressBar, ProgressStyle};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::model::baseline::ConvGeneratorConfig;
use crate::model::data::RangeDataset;
use crate::model::discriminator::{Discriminator, DiscriminatorConfig};
use crate::model::generator::{Generator, GeneratorConfig, GridCache, random_subgrid_shift};
use crate::model::measurement::MeasurementConfig;
use crate::model::rng::{Rng, tensor_from, tensor_to_vec};
use crate::model::{AnyGenerator, Arch, Generated, ModelConfig};

use super::growth::{Level, Stage, stage_at};
use super::reconstruct::{self, InLoopEncoder, Losses, ReconstructionConfig};

/// The burn backend a training run computes on. The CPU ones are always built;
/// the GPU ones need the cargo feature of the same name (`--features cuda` or
/// `--features wgpu`), so the default build needs no GPU toolkit.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Backend {
    Flex,
    Ndarray,
    Cuda,
    Wgpu,
}

impl Backend {
    pub const ALL: [Backend; 4] = [
        Backend::Flex,
        Backend::Ndarray,
        Backend::Cuda,
        Backend::Wgpu,
    ];

    /// The device to compute on, or why this build has none for this backend.
    pub fn device(self) -> Result<Device> {
        match self {
            Backend::Flex => Ok(Device::flex()),
            #[allow(deprecated)]
            Backend::Ndarray => Ok(Device::ndarray()),
            #[cfg(feature = "cuda")]
            Backend::Cuda => Ok(Device::cuda(0)),
            #[cfg(feature = "wgpu")]
            Backend::Wgpu => Ok(Device::wgpu(burn::tensor::DeviceKind::DefaultDevice)),
            #[allow(unreachable_patterns)]
            gpu => bail!(
                "this rangegan-mcap was built without the `{0}` feature; \
                 rebuild with `cargo build --release --features {0}` to train on {0}",
                gpu.name()
            ),
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Backend::Flex => "flex",
            Backend::Ndarray => "ndarray",
            Backend::Cuda => "cuda",
            Backend::Wgpu => "wgpu",
        }
    }
}

impl std::str::FromStr for Backend {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        Backend::ALL
            .into_iter()
            .find(|b| b.name() == s)
            .ok_or_else(|| format!("unknown backend {s:?}: use flex, ndarray, cuda or wgpu"))
    }
}

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
}

/// How to run training (not part of the saved config).
#[derive(Debug, Clone)]
pub struct TrainOptions {
    pub run_dir: PathBuf,
    /// Dataset cache file (built from `scans` if missing).
    pub dataset_cache: PathBuf,
    /// KITTI `.bin` scans to build the cache from.
    pub scans: Vec<PathBuf>,
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
}

pub use crate::model::weights::CHECKPOINT;

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
    Ok(serde_json::from_value(merged)?)
}

/// Train (or resume) in `opts.run_dir`.
pub fn run(opts: &TrainOptions) -> Result<()> {
    std::fs::create_dir_all(opts.run_dir.join("snapshots"))
        .with_context(|| format!("failed to create '{}'", opts.run_dir.display()))?;
    let config_path = opts.run_dir.join("config.json");
    let config = if config_path.exists() {
        load_config(&config_path)?
    } else {
        opts.config
            .save(&config_path)
            .with_context(|| format!("failed to write '{}'", config_path.display()))?;
        opts.config.clone()
    };
    let config = match opts.total_images {
        Some(n) if n != config.total_images => {
            let c = config.with_total_images(n);
            c.save(&config_path)
                .with_context(|| format!("failed to write '{}'", config_path.display()))?;
            c
        }
        _ => config,
    };
    let data = RangeDataset::load_or_build(&opts.dataset_cache, &opts.scans, 512)?;
    if data.len() < config.batch_size {
        bail!("dataset has {} images, fewer than a batch", data.len());
    }
    if !config.stages.is_empty() {
        ensure!(
            config.arch == Arch::Dusty2 && !config.drop_head_only,
            "coarse-to-fine stages need a dusty2 generator trained whole"
        );
        super::growth::check_stages(
            &config.stages,
            config.generator.channels.len(),
            (data.height, data.width),
            |stage| {
                let d = config.discriminator_of(stage);
                d.stem.max(1) << d.channels.len().saturating_sub(1)
            },
        )?;
    }
    let mut trainer = Trainer::new(&config, opts, &data)?;
    trainer.train(opts, &data)
}

struct Trainer {
    config: TrainConfig,
    device: Device,
    g: AnyGenerator,
    g_ema: AnyGenerator,
    d: Discriminator,
    opt_g: ModuleOptimizer,
    opt_d: ModuleOptimizer,
    state: TrainState,
    /// The generator's grid caches (autodiff and inner device) on the full grid; the
    /// current level renders the first blocks of them.
    full_grid: Option<(GridCache, GridCache)>,
    grid: Option<GridCache>,
    grid_inner: Option<GridCache>,
    /// The resolution of the current coarse-to-fine stage.
    level: Level,
    /// The encoder of reconstruction-assisted training, at the current level.
    encoder: Option<InLoopEncoder>,
    snapshot_z: Tensor<2>,
    /// The latest (lazy) R1 estimate, logged on every log line.
    last_r1: Option<f32>,
}

impl Trainer {
    fn new(config: &TrainConfig, opts: &TrainOptions, data: &RangeDataset) -> Result<Self> {
        let inner = opts.backend.device()?;
        let device = inner.clone().autodiff();
        let adam = AdamConfig::new()
            .with_beta_1(config.beta1)
            .with_beta_2(config.beta2)
            .with_epsilon(1e-8);
        let mut g = init_generator(config, &device);
        let mut g_ema = init_generator(config, &inner);
        let mut opt_g = adam.init();
        let mut opt_d = adam.init();
        let ck = opts.run_dir.join(CHECKPOINT);
        let resumed = ck.join("state.json").exists();
        let state = if resumed {
            let text = std::fs::read_to_string(ck.join("state.json"))?;
            serde_json::from_str(&text).context("bad checkpoint/state.json")?
        } else {
            TrainState {
                step: 0,
                images: 0,
                ada_p: 0.0,
                rng: Rng::new(config.seed),
                ada_acc: 0.0,
                ada_count: 0,
                stage: 0,
                stage_start_images: 0,
            }
        };
        let level = Level::of(
            &config.stages,
            state.stage,
            config.generator.channels.len(),
            data.height,
            data.width,
        );
        let mut d = stage_discriminator(config, state.stage, &level, &device);
        let mut encoder = in_loop_encoder(config, &level, &device);
        if resumed {
            let load_err = |what: &str, e: burn::store::RecordError| {
                anyhow::anyhow!("failed to load {what} from '{}': {e}", ck.display())
            };
            g = g
                .try_load_file(ck.join("g.bpk"))
                .map_err(|e| load_err("g", e))?;
            g_ema = g_ema
                .try_load_file(ck.join("g_ema.bpk"))
                .map_err(|e| load_err("g_ema", e))?;
            d = d
                .try_load_file(ck.join("d.bpk"))
                .map_err(|e| load_err("d", e))?;
            opt_g = opt_g
                .load(ck.join("opt_g.bpk"))
                .map_err(|e| load_err("opt_g", e))?;
            // A compact checkpoint (the committed one) may leave out D's Adam state: it is
            // rebuilt within a few dozen steps (beta1 = 0), and at 64 x 512 it is most of the bytes.
            if ck.join("opt_d.bpk").exists() {
                opt_d = opt_d
                    .load(ck.join("opt_d.bpk"))
                    .map_err(|e| load_err("opt_d", e))?;
            }
            if let Some(e) = encoder.as_mut().filter(|_| ck.join("e.bpk").exists()) {
                e.encoder = e
                    .encoder
                    .clone()
                    .try_load_file(ck.join("e.bpk"))
                    .map_err(|err| load_err("e", err))?;
                e.opt = std::mem::replace(&mut e.opt, AdamConfig::new().init())
                    .load(ck.join("opt_e.bpk"))
                    .map_err(|err| load_err("opt_e", err))?;
            }
        } else if let Some(src) = &opts.init_from {
            // A discriminator of another shape than the source's starts fresh.
            let same_d = level.factor == 1
                && load_config(&src.join("config.json")).is_ok_and(|c| {
                    serde_json::to_value(&c.discriminator).ok()
                        == serde_json::to_value(&config.discriminator).ok()
                });
            (g, g_ema, d) = init_from(src, g, g_ema, d, same_d, config.drop_head_only)?;
            std::fs::write(
                opts.run_dir.join("init_from.json"),
                serde_json::to_string_pretty(&serde_json::json!({
                    "init_from": src,
                    "source_state": std::fs::read_to_string(src.join(CHECKPOINT).join("state.json"))
                        .ok()
                        .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok()),
                }))?,
            )?;
        } else {
            // The EMA starts as a copy of the generator.
            g_ema = g.valid();
        }
        let full_grid = match &g {
            AnyGenerator::Implicit(generator) => Some((
                generator.prepare(&data.angles, &device),
                generator.prepare(&data.angles, &inner),
            )),
            AnyGenerator::Conv(_) => None,
        };
        let snapshot_z = Rng::new(config.seed ^ 0x5eed).normal_tensor([4, g.d_z()], &inner);
        let mut trainer = Self {
            config: config.clone(),
            device,
            g,
            g_ema,
            d,
            opt_g,
            opt_d,
            state,
            full_grid,
            grid: None,
            grid_inner: None,
            level,
            encoder,
            snapshot_z,
            last_r1: None,
        };
        trainer.cut_grids();
        Ok(trainer)
    }

    /// The grid caches of the current level.
    fn cut_grids(&mut self) {
        (self.grid, self.grid_inner) = match &self.full_grid {
            Some((grid, inner)) => (Some(self.level.grid(grid)), Some(self.level.grid(inner))),
            None => (None, None),
        };
    }

    /// Moves to the next coarse-to-fine stage once the images seen reach it: one more block
    /// renders, on a grid twice as fine, against a fresh discriminator of that size.
    fn grow(&mut self, data: &RangeDataset) -> bool {
        let stage = stage_at(&self.config.stages, self.state.images);
        if stage <= self.state.stage {
            return false;
        }
        let blocks = self.config.generator.channels.len();
        self.state.stage = stage;
        self.state.stage_start_images = self.state.images;
        self.level = Level::of(&self.config.stages, stage, blocks, data.height, data.width);
        self.d = stage_discriminator(&self.config, stage, &self.level, &self.device);
        self.encoder = in_loop_encoder(&self.config, &self.level, &self.device);
        self.opt_d = AdamConfig::new()
            .with_beta_1(self.config.beta1)
            .with_beta_2(self.config.beta2)
            .with_epsilon(1e-8)
            .init();
        self.cut_grids();
        true
    }

    /// Whether the generator sits out this step: a fresh discriminator learns first.
    fn d_warming_up(&self) -> bool {
        self.state.stage > 0
            && self.state.images < self.state.stage_start_images + self.config.d_warmup_images
    }

    fn train(&mut self, opts: &TrainOptions, data: &RangeDataset) -> Result<()> {
        let cfg = self.config.clone();
        let b = cfg.batch_size;
        let bar = if opts.progress {
            ProgressBar::new(cfg.total_images)
        } else {
            ProgressBar::hidden()
        };
        bar.set_style(
            ProgressStyle::with_template(
                "{elapsed_precise} [{bar:30}] {human_pos}/{human_len} img {msg}",
            )
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        bar.set_position(self.state.images);
        let log_path = opts.run_dir.join("log.jsonl");
        let mut log = OpenOptions::new()
            .create(true)
            .append(true)
            .open(&log_path)
            .with_context(|| format!("failed to open '{}'", log_path.display()))?;
        let started = Instant::now();
        let mut last_ckpt = Instant::now();
        let mut window = (Instant::now(), self.state.images);
        let mut next_snapshot =
            (self.state.images / cfg.snapshot_every_images + 1) * cfg.snapshot_every_images;
        if self.state.images == 0 {
            self.snapshot(opts, data)?;
        }
        while self.state.images < cfg.total_images {
            let m = self.step(data)?;
            self.state.step += 1;
            self.state.images += b as u64;
            if self.grow(data) {
                // The fresh discriminator's start is a checkpoint of its own.
                self.checkpoint(&opts.run_dir)?;
                last_ckpt = Instant::now();
            }
            bar.set_position(self.state.images);
            if self.state.step.is_multiple_of(cfg.log_every_steps) {
                let dt = window.0.elapsed().as_secs_f64();
                let ips = (self.state.images - window.1) as f64 / dt.max(1e-9);
                window = (Instant::now(), self.state.images);
                bar.set_message(format!(
                    "{ips:.1} img/s  D {:.3}  G {:.3}  p {:.2}",
                    m.loss_d, m.loss_g, self.state.ada_p
                ));
                let line = serde_json::json!({
                    "step": self.state.step,
                    "images": self.state.images,
                    "loss_d": m.loss_d,
                    "loss_g": m.loss_g,
                    "r1": m.r1.or(self.last_r1),
                    "d_real": m.d_real,
                    "d_fake": m.d_fake,
                    "ada_p": self.state.ada_p,
                    "pixel_drop": m.pixel_drop,
                    "images_per_s": ips,
                    "stage": self.state.stage,
                    "reconstruction": m.assisted.map(|a| a.reconstruction),
                    "cycle": m.assisted.map(|a| a.cycle),
                    "grid": [self.level.height, self.level.width],
                    "elapsed_s": started.elapsed().as_secs_f64(),
                });
                writeln!(log, "{line}")?;
            }
            if self.state.images >= next_snapshot {
                next_snapshot += cfg.snapshot_every_images;
                self.snapshot(opts, data)?;
                self.checkpoint(&opts.run_dir)?;
                last_ckpt = Instant::now();
            }
            if last_ckpt.elapsed() >= Duration::from_secs(cfg.checkpoint_every_secs) {
                self.checkpoint(&opts.run_dir)?;
                last_ckpt = Instant::now();
            }
            if opts.max_duration.is_some_and(|t| started.elapsed() >= t) {
                break;
            }
        }
        self.checkpoint(&opts.run_dir)?;
        self.snapshot(opts, data)?;
        bar.finish();
        Ok(())
    }

    /// Probability of the early random pixel dropout now.
    fn pixel_drop(&self) -> f32 {
        let t = self.state.images as f64 / self.config.pixel_drop_images.max(1.0);
        (self.config.pixel_drop_start as f64 * (1.0 - t).max(0.0)) as f32
    }

    fn real_batch(&mut self, data: &RangeDataset, device: &Device) -> Tensor<4> {
        let b = self.config.batch_size;
        let level = self.level;
        let mut v = Vec::with_capacity(b * level.height * level.width);
        for _ in 0..b {
            let i = self.state.rng.below(data.len());
            if level.factor == 1 {
                v.extend_from_slice(data.image(i));
            } else {
                let phase = level.random_phase(&mut self.state.rng);
                v.extend(level.sample(data.image(i), data.width, phase));
            }
        }
        tensor_from(v, [b, 1, level.height, level.width], device)
    }

    fn z(&mut self, device: &Device) -> Tensor<2> {
        let d_z = self.g.d_z();
        self.state
            .rng
            .normal_tensor([self.config.batch_size, d_z], device)
    }

    fn subgrid(&mut self) -> Option<Vec<f32>> {
        (self.config.subgrid && self.config.arch == Arch::Dusty2)
            .then(|| random_subgrid_shift(&mut self.state.rng, self.config.batch_size))
    }

    fn step(&mut self, data: &RangeDataset) -> Result<StepMetrics> {
        let cfg = self.config.clone();
        let device = self.device.clone();
        let inner = device.clone().inner();
        let parts = batch_parts(cfg.batch_size);

        // ---- D step: fakes come from the generator without autodiff (constants for D).
        let z = self.z(&inner);
        let shift = self.subgrid();
        let real = self.real_batch(data, &device);
        let lazy = cfg.r1_gamma > 0.0 && self.state.step.is_multiple_of(cfg.r1_interval as u64);
        let view = DView {
            pixel_drop: self.pixel_drop(),
            ada_p: self.state.ada_p,
        };
        let n = cfg.batch_size / parts;
        let seeds: Vec<u64> = (0..parts).map(|_| self.state.rng.next_u64()).collect();
        let r1_gamma = self.level.r1_gamma(cfg.r1_gamma);
        let g_inner = self.g.valid();
        let d_parts: Vec<DPart> = (0..parts)
            .into_par_iter()
            .map(|k| {
                let mut rng = Rng::new(seeds[k]);
                let z = z.clone().narrow(0, k * n, n);
                let shift = shift.as_ref().map(|s| &s[k * n..(k + 1) * n]);
                let (fake, _) = g_inner.generate(z, self.grid_inner.as_ref(), shift);
                let fake = measure(&cfg.measurement, fake, &mut rng).autodiff();
                let fake = view.apply(fake, &mut rng);
                let real = view.apply(real.clone().narrow(0, k * n, n), &mut rng);
                let v = lazy.then(|| rng.normal_tensor(real.dims(), &device));
                d_part(&self.d, &device, &cfg, r1_gamma, fake, real, v)
            })
            .collect();
        let mean = |f: &dyn Fn(&DPart) -> f32| d_parts.iter().map(f).sum::<f32>() / parts as f32;
        let (loss_d, d_fake) = (mean(&|p| p.loss_d), mean(&|p| p.d_fake));
        let r1 = lazy.then(|| mean(&|p| p.r1.unwrap_or(0.0)));
        let d_real: Vec<f32> = d_parts.iter().flat_map(|p| p.d_real.clone()).collect();
        if r1.is_some() {
            self.last_r1 = r1;
        }
        let grads = mean_grads(&self.d, d_parts.into_iter().map(|p| p.grads).collect());
        self.d = self.opt_d.step(cfg.lr, self.d.clone(), grads);

        // Adaptive augmentation: move p towards E[sign(D(real))] = target.
        self.state.ada_acc += d_real.iter().map(|v| v.signum()).sum::<f32>();
        self.state.ada_count += d_real.len() as u64;
        if self.state.step.is_multiple_of(cfg.ada_interval as u64) && self.state.ada_count > 0 {
            let rt = self.state.ada_acc / self.state.ada_count as f32;
            let delta = (cfg.batch_size * cfg.ada_interval) as f64 / cfg.ada_speed_images;
            let p = self.state.ada_p + (rt - cfg.ada_target).signum() * delta as f32;
            self.state.ada_p = p.clamp(0.0, 1.0);
            self.state.ada_acc = 0.0;
            self.state.ada_count = 0;
        }

        let (loss_g, assisted) =
            if self.d_warming_up() || !self.state.step.is_multiple_of(cfg.g_every.max(1) as u64) {
                (f32::NAN, None)
            } else {
                self.g_step(view, data)
            };
        Ok(StepMetrics {
            loss_d,
            loss_g,
            r1,
            d_real: d_real.iter().sum::<f32>() / d_real.len() as f32,
            d_fake,
            pixel_drop: self.pixel_drop(),
            assisted,
        })
    }

    /// The generator's step (D without autodiff on its weights still passes gradients to
    /// its input), then its EMA; returns G's loss.
    fn g_step(&mut self, view: DView, data: &RangeDataset) -> (f32, Option<Losses>) {
        let cfg = self.config.clone();
        let device = self.device.clone();
        let parts = batch_parts(cfg.batch_size);
        let n = cfg.batch_size / parts;
        let z = self.z(&device);
        let shift = self.subgrid();
        let d_frozen = self.d.valid();
        let view = DView {
            ada_p: self.state.ada_p,
            ..view
        };
        let seeds: Vec<u64> = (0..parts).map(|_| self.state.rng.next_u64()).collect();
        // Reconstruction-assisted runs encode a batch of real scans as well.
        let real = self
            .encoder
            .is_some()
            .then(|| self.real_batch(data, &device));
        let rendering = self.rendering_generator();
        let mut g_parts: Vec<GPart> = (0..parts)
            .into_par_iter()
            .map(|k| {
                let g = rendering.clone().fork(&device);
                let z = z.clone().narrow(0, k * n, n);
                let shift = shift.as_ref().map(|s| &s[k * n..(k + 1) * n]);
                let (fake, w) = g.generate(z, self.grid.as_ref(), shift);
                let mut rng = Rng::new(seeds[k]);
                let fake = measure(&cfg.measurement, fake, &mut rng);
                let logit = d_frozen.forward(view.apply(fake.clone(), &mut rng));
                let loss_g = softplus(logit.neg(), 1.0).mean();
                let loss = loss_g.clone().inner().into_scalar::<f32>();
                let encoder = self
                    .encoder
                    .as_ref()
                    .map(|e| e.encoder.clone().fork(&device));
                let (total, assisted) = match (&g, &encoder, &real, &w) {
                    (AnyGenerator::Implicit(generator), Some(e), Some(real), Some(w)) => {
                        let grid = self
                            .grid
                            .as_ref()
                            .expect("the implicit generator has a grid");
                        let real = real.clone().narrow(0, k * n, n);
                        let (extra, values) = reconstruct::losses(
                            cfg.reconstruction
                                .as_ref()
                                .expect("an encoder has its config"),
                            generator,
                            e,
                            grid,
                            real,
                            fake,
                            w.clone(),
                        );
                        (loss_g + extra, Some(values))
                    }
                    _ => (loss_g, None),
                };
                let mut grads = total.backward();
                GPart {
                    grads: GradientsParams::from_module(&mut grads, &g),
                    encoder_grads: encoder
                        .as_ref()
                        .map(|e| GradientsParams::from_module(&mut grads, e)),
                    loss,
                    w: w.map(|w| w.detach()),
                    assisted,
                }
            })
            .collect();
        let loss_g = g_parts.iter().map(|p| p.loss).sum::<f32>() / parts as f32;
        let assisted = self.encoder_step(&mut g_parts);
        let w: Option<Vec<Tensor<2>>> = g_parts.iter().map(|p| p.w.clone()).collect();
        let w = w.map(|w| Tensor::cat(w, 0));
        let grads = mean_grads(&self.g, g_parts.into_iter().map(|p| p.grads).collect());
        let grads = if cfg.drop_head_only {
            drop_head_grads(&self.g, grads)
        } else {
            grads
        };
        let g = self
            .opt_g
            .step(cfg.g_lr.unwrap_or(cfg.lr), self.g.clone(), grads);
        // A frozen mapping keeps its w average too: the decode starts from it.
        let w = w.filter(|_| !cfg.drop_head_only);
        self.g = match (g, w) {
            (AnyGenerator::Implicit(mut generator), Some(w)) => {
                generator.mapping = generator.mapping.track_w_avg(&w);
                AnyGenerator::Implicit(generator)
            }
            (g, _) => g,
        };

        // ---- EMA of the generator (inference model).
        let half_life = cfg
            .ema_half_life_images
            .min(self.state.images as f64 * cfg.ema_rampup)
            .max(1.0);
        let beta = 0.5f64.powf(cfg.batch_size as f64 / half_life) as f32;
        self.g_ema = ema_update(self.g_ema.clone(), &self.g, beta);
        (loss_g, assisted)
    }

    /// The generator as the current stage renders: the first blocks only. Blocks that take
    /// no part must not enter the autodiff graph either: a tracked parameter that no backward
    /// pass ever consumes stays registered, and every later backward pass walks it again (a
    /// run slowed from 115 to 33 images/s in 1 400 steps that way).
    fn rendering_generator(&self) -> AnyGenerator {
        match &self.g {
            AnyGenerator::Implicit(g) if self.level.blocks < g.blocks.len() => {
                AnyGenerator::Implicit(Generator {
                    mapping: g.mapping.clone(),
                    blocks: g.blocks[..self.level.blocks].to_vec(),
                    output_gain: g.output_gain,
                })
            }
            g => g.clone(),
        }
    }

    /// The in-loop encoder's Adam step on the parts' mean gradient; the parts' mean losses.
    fn encoder_step(&mut self, parts: &mut [GPart]) -> Option<Losses> {
        let lr = self.config.reconstruction.as_ref()?.lr;
        let e = self.encoder.as_mut()?;
        let grads: Vec<GradientsParams> = parts
            .iter_mut()
            .filter_map(|p| p.encoder_grads.take())
            .collect();
        let grads = mean_grads(&e.encoder, grads);
        e.encoder = e.opt.step(lr, e.encoder.clone(), grads);
        let k = parts.len().max(1) as f32;
        let values = parts.iter().filter_map(|p| p.assisted);
        Some(values.fold(Losses::default(), |acc, v| Losses {
            reconstruction: acc.reconstruction + v.reconstruction / k,
            cycle: acc.cycle + v.cycle / k,
        }))
    }

    /// Write the checkpoint (a kill never leaves half a one).
    fn checkpoint(&self, run_dir: &Path) -> Result<()> {
        write_checkpoint(run_dir, |tmp| {
            let save_err = |what: &str, e: burn::store::RecordError| {
                anyhow::anyhow!("failed to save {what}: {e}")
            };
            self.g
                .clone()
                .save_file(tmp.join("g.bpk"))
                .map_err(|e| save_err("g", e))?;
            self.g_ema
                .clone()
                .save_file(tmp.join("g_ema.bpk"))
                .map_err(|e| save_err("g_ema", e))?;
            self.d
                .clone()
                .save_file(tmp.join("d.bpk"))
                .map_err(|e| save_err("d", e))?;
            self.opt_g
                .save(tmp.join("opt_g.bpk"))
                .map_err(|e| save_err("opt_g", e))?;
            self.opt_d
                .save(tmp.join("opt_d.bpk"))
                .map_err(|e| save_err("opt_d", e))?;
            if let Some(e) = &self.encoder {
                e.encoder
                    .clone()
                    .save_file(tmp.join("e.bpk"))
                    .map_err(|err| save_err("e", err))?;
                e.opt
                    .save(tmp.join("opt_e.bpk"))
                    .map_err(|err| save_err("opt_e", err))?;
            }
            std::fs::write(
                tmp.join("state.json"),
                serde_json::to_string_pretty(&self.state)?,
            )?;
            Ok(())
        })
    }

    /// PNG: for 4 fixed latents (EMA generator) the rows x_d | x_n (drop prob) | x_G, then
    /// 2 real scans.
    fn snapshot(&mut self, opts: &TrainOptions, data: &RangeDataset) -> Result<()> {
        let (h, w) = (self.level.height, self.level.width);
        let (out, _) = self
            .g_ema
            .generate(self.snapshot_z.clone(), self.grid_inner.as_ref(), None);
        let x_d = tensor_to_vec(out.x_d.clone());
        let (x_n, x_g) = match out.keep_logit.clone() {
            Some(logit) => {
                let keep = tensor_to_vec(burn::tensor::activation::sigmoid(logit.clone()));
                let x_n: Vec<f32> = keep.iter().map(|k| 2.0 * (1.0 - k) - 1.0).collect();
                let mut rng = Rng::new(self.state.step);
                let m = self.config.measurement.measure(out.x_d, logit, &mut rng);
                (x_n, tensor_to_vec(m.x_measured))
            }
            None => (vec![-1.0; x_d.len()], x_d.clone()),
        };
        let n = h * w;
        let mut rows: Vec<&[f32]> = Vec::new();
        for i in 0..4 {
            rows.push(&x_d[i * n..(i + 1) * n]);
            rows.push(&x_n[i * n..(i + 1) * n]);
            rows.push(&x_g[i * n..(i + 1) * n]);
        }
        let reals =
            [0, data.len() / 2].map(|i| self.level.sample(data.image(i), data.width, (0, 0)));
        rows.extend(reals.iter().map(|r| r.as_slice()));
        let path = opts
            .run_dir
            .join("snapshots")
            .join(format!("{:09}.png", self.state.images));
        write_png(&path, &rows, h, w)
    }
}

/// A fresh discriminator for `level`'s resolution.
fn stage_discriminator(
    config: &TrainConfig,
    stage: usize,
    level: &Level,
    device: &Device,
) -> Discriminator {
    config
        .discriminator_of(stage)
        .clone()
        .with_height(level.height)
        .with_width(level.width)
        .init(device)
}

impl TrainConfig {
    /// The generator this run trains, as its model folder's config describes it.
    pub fn model(&self) -> ModelConfig {
        ModelConfig {
            arch: self.arch,
            generator: self.generator.clone(),
            conv_generator: self.conv_generator.clone(),
            measurement: self.measurement.clone(),
        }
    }

    /// The discriminator configuration of coarse-to-fine stage `stage`.
    pub fn discriminator_of(&self, stage: usize) -> &DiscriminatorConfig {
        self.stage_discriminators
            .get(stage)
            .filter(|_| stage < self.stages.len())
            .unwrap_or(&self.discriminator)
    }
}

/// The in-loop encoder for `level` where the run is reconstruction-assisted.
fn in_loop_encoder(config: &TrainConfig, level: &Level, device: &Device) -> Option<InLoopEncoder> {
    let d_w = config.generator.mapping.d_w;
    config
        .reconstruction
        .as_ref()
        .filter(|_| config.arch == Arch::Dusty2)
        .map(|r| InLoopEncoder::new(r, level, d_w, device))
}

/// The weights of a fine-tuning run's start: from a training run's checkpoint (G, EMA G,
/// and D where `load_d`), or from a model directory (`g_ema.bpk`: G and EMA G). A D not
/// loaded keeps its fresh weights. `g_from_ema`: G starts as the EMA generator too, so
/// whatever training leaves frozen stays the EMA's.
fn init_from(
    src: &Path,
    g: AnyGenerator,
    g_ema: AnyGenerator,
    d: Discriminator,
    load_d: bool,
    g_from_ema: bool,
) -> Result<(AnyGenerator, AnyGenerator, Discriminator)> {
    let err = |what: &str, e: burn::store::RecordError| {
        anyhow::anyhow!("failed to load {what} from '{}': {e}", src.display())
    };
    let ck = src.join(CHECKPOINT);
    if ck.join("g.bpk").exists() {
        let g_file = if g_from_ema { "g_ema.bpk" } else { "g.bpk" };
        let g = g.try_load_file(ck.join(g_file)).map_err(|e| err("g", e))?;
        let g_ema = g_ema
            .try_load_file(ck.join("g_ema.bpk"))
            .map_err(|e| err("g_ema", e))?;
        let d = if load_d {
            d.try_load_file(ck.join("d.bpk")).map_err(|e| err("d", e))?
        } else {
            d
        };
        Ok((g, g_ema, d))
    } else {
        let file = src.join("g_ema.bpk");
        if !file.exists() {
            bail!(
                "'{}' holds neither a training checkpoint nor g_ema.bpk",
                src.display()
            );
        }
        let g = g.try_load_file(&file).map_err(|e| err("g_ema", e))?;
        let g_ema = g_ema.try_load_file(&file).map_err(|e| err("g_ema", e))?;
        Ok((g, g_ema, d))
    }
}

struct StepMetrics {
    loss_d: f32,
    loss_g: f32,
    r1: Option<f32>,
    d_real: f32,
    d_fake: f32,
    pixel_drop: f32,
    /// Reconstruction-assisted runs: the reconstruction and latent-cycle losses.
    assisted: Option<Losses>,
}

/// One part of a G step: its gradients (and the in-loop encoder's) and numbers.
struct GPart {
    grads: GradientsParams,
    encoder_grads: Option<GradientsParams>,
    loss: f32,
    w: Option<Tensor<2>>,
    assisted: Option<Losses>,
}

/// How many parts a batch is split into: each part runs forward and backward on its own
/// autodiff graph (a fork of the module), in parallel where there are threads, since a
/// step's small convolutions alone leave most of a second core idle. Always two for an
/// even batch, so results do not depend on the thread count.
fn batch_parts(batch: usize) -> usize {
    if batch >= 2 && batch.is_multiple_of(2) {
        2
    } else {
        1
    }
}

/// x_G of the generator output (measurement model unless vanilla).
fn measure(measurement: &MeasurementConfig, out: Generated, rng: &mut Rng) -> Tensor<4> {
    match out.keep_logit {
        Some(logit) => measurement.measure(out.x_d, logit, rng).x_measured,
        None => out.x_d,
    }
}

/// What D sees: early pixel dropout then augmentation (same for real and fake).
#[derive(Debug, Clone, Copy)]
struct DView {
    pixel_drop: f32,
    ada_p: f32,
}

impl DView {
    fn apply(self, x: Tensor<4>, rng: &mut Rng) -> Tensor<4> {
        let x = if self.pixel_drop > 0.0 {
            let keep = rng
                .uniform_open_tensor(x.dims(), &x.device())
                .greater_elem(self.pixel_drop)
                .float();
            (x.add_scalar(1.0) * keep).sub_scalar(1.0)
        } else {
            x
        };
        if self.ada_p > 0.0 {
            augment(x, self.ada_p, rng)
        } else {
            x
        }
    }
}

/// One part of a D step: its gradients and numbers.
struct DPart {
    grads: GradientsParams,
    loss_d: f32,
    r1: Option<f32>,
    d_real: Vec<f32>,
    d_fake: f32,
}

/// D's loss on one part of the batch (with the lazy finite-difference R1 of weight
/// `r1_gamma` where `v` is given) and its gradients, on a fork of `d`.
fn d_part(
    d: &Discriminator,
    device: &Device,
    cfg: &TrainConfig,
    r1_gamma: f32,
    fake: Tensor<4>,
    real: Tensor<4>,
    v: Option<Tensor<4>>,
) -> DPart {
    let d = d.clone().fork(device);
    let logit_fake = d.forward(fake); // [part, 1]
    let logit_real = d.forward(real.clone()); // [part, 1]
    let d_real = tensor_to_vec(logit_real.clone().inner());
    let d_fake = tensor_to_vec(logit_fake.clone().inner());
    let loss_d = softplus(logit_fake, 1.0).mean() + softplus(logit_real.clone().neg(), 1.0).mean();
    let (total, r1) = match v {
        Some(v) => {
            // Finite-difference R1: with v ~ N(0, I), E[(grad D . v)^2] = |grad D|^2, and
            // (D(x + h v) - D(x)) / h estimates grad D . v with first-order autodiff only.
            let h = cfg.r1_fd_step;
            let moved = d.forward(real.detach() + v.mul_scalar(h)); // [part, 1]
            let r1 = (moved - logit_real).div_scalar(h).powi_scalar(2).mean();
            let penalty = r1
                .clone()
                .mul_scalar(r1_gamma * 0.5 * cfg.r1_interval as f32);
            let r1 = r1.inner().into_scalar::<f32>();
            (loss_d.clone() + penalty, Some(r1))
        }
        None => (loss_d.clone(), None),
    };
    DPart {
        grads: GradientsParams::from_grads(total.backward(), &d),
        loss_d: loss_d.inner().into_scalar::<f32>(),
        r1,
        d_fake: d_fake.iter().sum::<f32>() / d_fake.len().max(1) as f32,
        d_real,
    }
}

/// The keep logit's output row in a generator head (row 0 is x_d before tanh).
const KEEP_LOGIT: usize = 1;

/// The gradients of the ray-drop logit alone: each synthesis block's head keeps the
/// gradient of its second output row (weight and bias), everything else has none, so
/// Adam leaves it exactly as it is.
fn drop_head_grads(g: &AnyGenerator, mut grads: GradientsParams) -> GradientsParams {
    let mut out = GradientsParams::new();
    let AnyGenerator::Implicit(generator) = g else {
        return out;
    };
    for head in generator.blocks.iter().map(|b| &b.head) {
        if let Some(w) = grads.remove::<2>(head.weight.id) {
            out.register(head.weight.id, keep_logit_only(w));
        }
        if let Some(b) = grads.remove::<1>(head.bias.id) {
            out.register(head.bias.id, keep_logit_only(b));
        }
    }
    out
}

/// A head parameter's gradient with every output row but the keep logit's zeroed.
fn keep_logit_only<const D: usize>(grad: Tensor<D>) -> Tensor<D> {
    let dims = grad.dims();
    let per_row = dims[1..].iter().product::<usize>();
    let mask: Vec<f32> = (0..dims[0] * per_row)
        .map(|i| if i / per_row == KEEP_LOGIT { 1.0 } else { 0.0 })
        .collect();
    let mask = tensor_from(mask, dims, &grad.device());
    grad * mask
}

/// The mean of the parts' gradients (each part's loss is a mean over its samples, so
/// the mean is the whole batch's gradient).
fn mean_grads<M: Module>(module: &M, parts: Vec<GradientsParams>) -> GradientsParams {
    struct Mean {
        parts: Vec<GradientsParams>,
        out: GradientsParams,
    }
    impl ModuleVisitor for Mean {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            let grads: Vec<Tensor<D>> = self
                .parts
                .iter_mut()
                .filter_map(|g| g.remove::<D>(param.id))
                .collect();
            let n = grads.len() as f32;
            if let Some(sum) = grads.into_iter().reduce(|a, b| a + b) {
                self.out.register(param.id, sum.div_scalar(n));
            }
        }
    }
    if parts.len() == 1 {
        return parts.into_iter().next().unwrap_or_default();
    }
    let mut mean = Mean {
        parts,
        out: GradientsParams::new(),
    };
    module.visit(&mut mean);
    mean.out
}

/// Writes `RUN_DIR/checkpoint/` through `fill` into a temporary folder, then swaps it in, so a
/// kill at any moment leaves the previous checkpoint or the new one, never half of one.
pub(crate) fn write_checkpoint(
    run_dir: &Path,
    fill: impl FnOnce(&Path) -> Result<()>,
) -> Result<()> {
    let tmp = run_dir.join("checkpoint.tmp");
    let old = run_dir.join("checkpoint.old");
    let dst = run_dir.join(CHECKPOINT);
    let _ = std::fs::remove_dir_all(&tmp);
    std::fs::create_dir_all(&tmp)?;
    fill(&tmp)?;
    let _ = std::fs::remove_dir_all(&old);
    if dst.exists() {
        std::fs::rename(&dst, &old)?;
    }
    std::fs::rename(&tmp, &dst)?;
    let _ = std::fs::remove_dir_all(&old);
    Ok(())
}

/// Stack `[H, W]` images (network units, -1 = black) vertically into one grayscale PNG,
/// with a gamma that keeps far (small inverse depth) pixels visible.
pub fn write_png(path: &Path, images: &[&[f32]], h: usize, w: usize) -> Result<()> {
    let mut pixels = Vec::with_capacity(images.len() * (h + 2) * w);
    for img in images {
        for v in img.iter() {
            let x = ((v + 1.0) * 0.5).clamp(0.0, 1.0).sqrt();
            pixels.push((x * 255.0).round() as u8);
        }
        pixels.extend(std::iter::repeat_n(128u8, 2 * w)); // separator
    }
    let file = std::fs::File::create(path)
        .with_context(|| format!("failed to create '{}'", path.display()))?;
    let mut enc = png::Encoder::new(
        std::io::BufWriter::new(file),
        w as u32,
        (images.len() * (h + 2)) as u32,
    );
    enc.set_color(png::ColorType::Grayscale);
    enc.set_depth(png::BitDepth::Eight);
    let mut writer = enc.write_header()?;
    writer.write_image_data(&pixels)?;
    writer.finish()?;
    Ok(())
}

/// Random augmentation with probability `p` per operation and sample. Only operations that
/// keep the circular structure: circular translation and mirroring along azimuth, vertical
/// scaling, brightness and contrast of the returns (dropped pixels stay -1). Geometric parts
/// are one batched `A_b x_b B_b` product with host-built matrices, so gradients flow to fakes.
///
/// # Shapes
/// - x: `[batch, 1, H, W]` -> `[batch, 1, H, W]`
pub fn augment(x: Tensor<4>, p: f32, rng: &mut Rng) -> Tensor<4> {
    let [b, c, h, w] = x.dims();
    let device = x.device();
    let mut rows = vec![0f32; b * h * h];
    let mut cols = vec![0f32; b * w * w];
    let mut gain = vec![1f32; b];
    let mut offset = vec![0f32; b];
    for i in 0..b {
        // columns: out[j] = x[src(j)]
        let flip = rng.uniform() < p;
        let shift = if rng.uniform() < p { rng.below(w) } else { 0 };
        for j in 0..w {
            let k = (j + w - shift) % w;
            let src = if flip { w - 1 - k } else { k };
            cols[i * w * w + src * w + j] = 1.0;
        }
        // rows: vertical scale about the centre, linear interpolation, clamped borders
        let scale = if rng.uniform() < p {
            (rng.normal() * 0.2 * std::f32::consts::LN_2).exp()
        } else {
            1.0
        };
        let centre = (h as f32 - 1.0) * 0.5;
        for r in 0..h {
            let y = ((r as f32 - centre) / scale + centre).clamp(0.0, (h - 1) as f32);
            let y0 = y.floor() as usize;
            let y1 = (y0 + 1).min(h - 1);
            let t = y - y0 as f32;
            rows[i * h * h + r * h + y0] += 1.0 - t;
            rows[i * h * h + r * h + y1] += t;
        }
        if rng.uniform() < p {
            offset[i] = rng.normal() * 0.2;
        }
        if rng.uniform() < p {
            gain[i] = (rng.normal() * 0.5 * std::f32::consts::LN_2).exp();
        }
    }
    let a = tensor_from(rows, [b, 1, h, h], &device);
    let m = tensor_from(cols, [b, 1, w, w], &device);
    let valid = x.clone().greater_elem(-1.0 + 1e-4).float(); // [batch, 1, H, W]
    let x = a.clone().matmul(x).matmul(m.clone()); // [batch, 1, H, W]
    let valid = a.matmul(valid).matmul(m).greater_elem(0.5).float();
    let gain = tensor_from(gain, [b, 1, 1, 1], &device);
    let offset = tensor_from(offset, [b, 1, 1, 1], &device);
    // contrast scales the inverse depth of returns, brightness shifts it
    let y = (x.add_scalar(1.0) * gain).sub_scalar(1.0) + offset;
    let y = (y.add_scalar(1.0) * valid).sub_scalar(1.0);
    debug_assert_eq!(c, 1);
    y
}

/// Collects a module's float parameters (flattened, no autodiff) in visit order.
struct Collect(Vec<(Tensor<1>, bool)>);

impl ModuleVisitor for Collect {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        let t = param.val();
        let trainable = t.is_require_grad();
        self.0.push((t.inner().reshape([-1]), trainable));
    }
}

/// ema <- beta ema + (1 - beta) g for trainable tensors; fixed tensors (Fourier frequencies,
/// w_avg) are copied.
struct Lerp {
    src: std::vec::IntoIter<(Tensor<1>, bool)>,
    beta: f32,
}

impl ModuleMapper for Lerp {
    fn map_float<const D: usize>(&mut self, param: Param<Tensor<D>>) -> Param<Tensor<D>> {
        let Some((src, trainable)) = self.src.next() else {
            return param;
        };
        let beta = self.beta;
        param.map(|e| {
            let src = src.reshape(e.shape());
            if trainable {
                e.mul_scalar(beta) + src.mul_scalar(1.0 - beta)
            } else {
                src
            }
        })
    }
}

/// `g` must live on an autodiff device (the training module): trainability is read from it.
pub fn ema_update<M: Module>(ema: M, g: &M, beta: f32) -> M {
    let mut c = Collect(Vec::new());
    g.visit(&mut c);
    ema.map(&mut Lerp {
        src: c.0.into_iter(),
        beta,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lidar::SensorProfile;
    use burn::module::ParamId;

    /// Every float parameter of a generator, in visiting order, with its id.
    /// A two-block generator and a small discriminator on the synthetic 64 x 64 scans,
    /// batch 2, lazy R1 every 2 steps: runs that take well under a second.
    fn tiny_run_config() -> TrainConfig {
        let generator = GeneratorConfig::new()
            .with_mapping(
                crate::model::generator::MappingConfig::new()
                    .with_d_z(8)
                    .with_d_w(8),
            )
            .with_channels(vec![8, 8])
            .with_n_freq(vec![4, 4])
            .with_lh(vec![4, 5])
            .with_lw(vec![3, 4]);
        TrainConfig::new()
            .with_generator(generator)
            .with_discriminator(DiscriminatorConfig::new().with_channels(vec![4, 8, 8]))
            .with_batch_size(2)
            .with_r1_interval(2)
    }

    /// Every float parameter's values, in module order (ids left out).
    fn module_values<M: Module>(m: &M) -> Vec<Vec<f32>> {
        struct Values(Vec<Vec<f32>>);
        impl ModuleVisitor for Values {
            fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
                self.0.push(tensor_to_vec(param.val()));
            }
        }
        let mut v = Values(Vec::new());
        m.visit(&mut v);
        v.0
    }

    fn generator_values(g: &AnyGenerator) -> Vec<(ParamId, Vec<f32>)> {
        struct Values(Vec<(ParamId, Vec<f32>)>);
        impl ModuleVisitor for Values {
            fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
                self.0.push((param.id, tensor_to_vec(param.val().inner())));
            }
        }
        let mut v = Values(Vec::new());
        g.visit(&mut v);
        v.0
    }

    #[test]
    fn backends_parse_by_name_and_the_cpu_ones_always_exist() {
        for b in Backend::ALL {
            assert_eq!(b.name().parse::<Backend>(), Ok(b));
            let json = serde_json::to_string(&b).expect("json");
            assert_eq!(json, format!("\"{}\"", b.name()));
        }
        assert!(Backend::Flex.device().is_ok());
        assert!(Backend::Ndarray.device().is_ok());
        assert!("tpu".parse::<Backend>().is_err());
    }

    #[cfg(not(feature = "cuda"))]
    #[test]
    fn a_gpu_backend_missing_from_the_build_says_which_feature_to_build() {
        let err = Backend::Cuda
            .device()
            .expect_err("no cuda in this build")
            .to_string();
        assert!(err.contains("--features cuda"), "{err}");
    }

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

    #[test]
    fn augment_keeps_drops_and_identity_at_p0() {
        let dev = Device::flex();
        let mut rng = Rng::new(1);
        let mut v = rng.uniform_vec(2 * 8 * 16);
        for (i, x) in v.iter_mut().enumerate() {
            if i % 5 == 0 {
                *x = -1.0;
            }
        }
        let x = tensor_from(v.clone(), [2, 1, 8, 16], &dev);
        let same = tensor_to_vec(augment(x.clone(), 0.0, &mut rng));
        assert!(same.iter().zip(&v).all(|(a, b)| (a - b).abs() < 1e-6));
        // A pure circular shift/flip keeps the number of dropped pixels.
        let y = tensor_to_vec(augment(x, 1.0, &mut rng));
        assert_eq!(y.len(), v.len());
        assert!(y.iter().all(|v| *v >= -1.0 - 1e-6));
    }

    #[test]
    fn ema_moves_towards_the_generator() {
        // The source is a training (autodiff) module: that is where trainability is known.
        let dev = Device::flex().autodiff();
        let cfg = TrainConfig::new().with_generator(
            GeneratorConfig::new()
                .with_mapping(
                    crate::model::generator::MappingConfig::new()
                        .with_d_z(4)
                        .with_d_w(4),
                )
                .with_channels(vec![4])
                .with_n_freq(vec![2])
                .with_lh(vec![3])
                .with_lw(vec![2]),
        );
        let a = init_generator(&cfg, &dev);
        let b = init_generator(
            &cfg.clone()
                .with_generator(cfg.generator.clone().with_seed(9)),
            &dev,
        );
        let mid = ema_update(a.clone(), &b, 0.5);
        let (AnyGenerator::Implicit(a), AnyGenerator::Implicit(b), AnyGenerator::Implicit(m)) =
            (a, b, mid)
        else {
            panic!("implicit expected");
        };
        let wa = tensor_to_vec(a.blocks[0].conv0.weight.val());
        let wb = tensor_to_vec(b.blocks[0].conv0.weight.val());
        let wm = tensor_to_vec(m.blocks[0].conv0.weight.val());
        for i in 0..wa.len() {
            assert!((wm[i] - 0.5 * (wa[i] + wb[i])).abs() < 1e-6);
        }
        // Fixed tensors are copied, not averaged.
        assert_eq!(
            tensor_to_vec(m.blocks[0].fourier.b_theta.val()),
            tensor_to_vec(b.blocks[0].fourier.b_theta.val())
        );
    }

    #[test]
    fn the_mean_of_the_parts_gradients_is_the_whole_batch_gradient() {
        let dev = Device::flex().autodiff();
        let cfg = TrainConfig::new()
            .with_arch(Arch::Vanilla)
            .with_conv_generator(
                ConvGeneratorConfig::new()
                    .with_d_z(6)
                    .with_channels(vec![8, 4])
                    .with_base_height(2)
                    .with_base_width(4),
            );
        let g = init_generator(&cfg, &dev);
        let z = Rng::new(5).normal_tensor([4, 6], &dev);
        let grads_of = |g: &AnyGenerator, z: Tensor<2>| {
            let g = g.clone().fork(&dev);
            let (out, _) = g.generate(z, None, None);
            let loss = out.x_d.powi_scalar(2).mean();
            GradientsParams::from_grads(loss.backward(), &g)
        };
        let whole = grads_of(&g, z.clone());
        let parts = (0..2)
            .map(|k| grads_of(&g, z.clone().narrow(0, 2 * k, 2)))
            .collect();
        let mean = mean_grads(&g, parts);
        let AnyGenerator::Conv(conv) = &g else {
            panic!("conv generator expected");
        };
        let id = conv.ups[0].weight.id;
        let (a, b) = (whole.get::<4>(id), mean.get::<4>(id));
        let (a, b) = (tensor_to_vec(a.unwrap()), tensor_to_vec(b.unwrap()));
        assert!(
            a.iter().any(|x| x.abs() > 1e-6),
            "a gradient that is zero tests nothing"
        );
        for (x, y) in a.iter().zip(&b) {
            assert!((x - y).abs() <= 1e-5 * (1.0 + x.abs()), "{x} vs {y}");
        }
        assert_eq!(batch_parts(8), 2);
        assert_eq!(batch_parts(5), 1);
    }

    /// A dataset cache of `n` 64 x 64 images in `dir`: each pixel dropped (-1) with
    /// probability 0.2, else `value(pixel index, rng)`.
    fn synthetic_cache(
        dir: &Path,
        n: usize,
        seed: u64,
        value: impl Fn(usize, &mut Rng) -> f32,
    ) -> PathBuf {
        let grid = SensorProfile::kitti_hdl64e().with_columns(64).angle_grid();
        let (h, w) = (grid.height, grid.width);
        let mut rng = Rng::new(seed);
        let images: Vec<f32> = (0..n * h * w)
            .map(|i| {
                if rng.uniform() < 0.2 {
                    -1.0
                } else {
                    value(i, &mut rng)
                }
            })
            .collect();
        let data = RangeDataset {
            height: h,
            width: w,
            images,
            angles: grid,
        };
        let cache = dir.join("ds.bin");
        data.save(&cache).expect("cache");
        cache
    }

    /// The baselines run through the same loop (fixed 64x64 output here).
    #[test]
    fn baselines_train_a_few_steps() {
        for arch in [Arch::Dusty1, Arch::Vanilla] {
            let dir = tempfile::tempdir().expect("tempdir");
            let (h, w) = (64, 64);
            let cache = synthetic_cache(dir.path(), 4, 4, |_, rng| rng.uniform() - 0.5);
            let config = TrainConfig::new()
                .with_arch(arch)
                .with_conv_generator(
                    ConvGeneratorConfig::new()
                        .with_d_z(8)
                        .with_channels(vec![8, 8, 8, 8, 8])
                        .with_base_width(4),
                )
                .with_discriminator(DiscriminatorConfig::new().with_channels(vec![4, 8, 8]))
                .with_batch_size(2)
                .with_r1_interval(1)
                .with_total_images(4)
                .with_snapshot_every_images(4);
            let opts = TrainOptions {
                run_dir: dir.path().join("run"),
                dataset_cache: cache,
                scans: vec![],
                config,
                backend: Backend::Flex,
                total_images: None,
                max_duration: None,
                progress: false,
                init_from: None,
            };
            run(&opts).expect("train");
            let (g, c) = load_generator(&opts.run_dir, &Device::flex()).expect("load");
            assert_eq!(c.arch, arch);
            let AnyGenerator::Conv(g) = g else {
                panic!("conv generator expected")
            };
            let z = Rng::new(1).normal_tensor([1, 8], &Device::flex());
            let channels = if arch == Arch::Vanilla { 1 } else { 2 };
            assert_eq!(g.forward(z).dims(), [1, channels, h, w]);
        }
    }

    /// A few steps on synthetic data, a checkpoint, and a resume that continues the count.
    #[test]
    fn trains_checkpoints_and_resumes() {
        let dir = tempfile::tempdir().expect("tempdir");
        let cache = synthetic_cache(dir.path(), 8, 3, |i, _| (i % 64) as f32 / 64.0 - 0.5);
        let data = RangeDataset::load(&cache).expect("cache");
        let (h, w) = (data.height, data.width);
        let config = tiny_run_config()
            .with_total_images(8)
            .with_snapshot_every_images(4)
            .with_ada_interval(1)
            .with_ada_speed_images(10.0);
        let mut opts = TrainOptions {
            run_dir: dir.path().join("run"),
            dataset_cache: cache,
            scans: vec![],
            config,
            backend: Backend::Flex,
            total_images: None,
            max_duration: None,
            progress: false,
            init_from: None,
        };
        run(&opts).expect("train");
        let state: TrainState = serde_json::from_str(
            &std::fs::read_to_string(opts.run_dir.join("checkpoint/state.json")).expect("state"),
        )
        .expect("json");
        assert_eq!(state.images, 8);
        let log = std::fs::read_to_string(opts.run_dir.join("log.jsonl")).expect("log");
        assert!(log.lines().count() >= 1 || state.step < 10);
        // Resume with a larger budget: continues from 8, not from 0.
        opts.total_images = Some(12);
        run(&opts).expect("resume");
        let state: TrainState = serde_json::from_str(
            &std::fs::read_to_string(opts.run_dir.join("checkpoint/state.json")).expect("state"),
        )
        .expect("json");
        assert_eq!(state.images, 12);
        // A compact checkpoint without the discriminator's optimiser state resumes too.
        std::fs::remove_file(opts.run_dir.join("checkpoint/opt_d.bpk")).expect("rm opt_d");
        opts.total_images = Some(16);
        run(&opts).expect("resume without opt_d");
        assert!(opts.run_dir.join("checkpoint/opt_d.bpk").exists());
        assert!(
            std::fs::read_dir(opts.run_dir.join("snapshots"))
                .expect("snapshots")
                .count()
                >= 2
        );
        let (g, _) = load_generator(&opts.run_dir, &Device::flex()).expect("load ema");
        assert_eq!(g.d_z(), 8);
        // Fine-tuning: a new run initialised from this one starts from its weights, at 0 images.
        let ft = TrainOptions {
            run_dir: dir.path().join("fine-tune"),
            init_from: Some(opts.run_dir.clone()),
            ..opts.clone()
        };
        std::fs::create_dir_all(&ft.run_dir).expect("mkdir");
        let t = Trainer::new(&ft.config, &ft, &data).expect("init from run");
        assert_eq!(t.state.images, 0);
        t.g_ema
            .clone()
            .save_file(ft.run_dir.join("start.bpk"))
            .expect("save");
        assert_eq!(
            std::fs::read(ft.run_dir.join("start.bpk")).expect("read"),
            std::fs::read(opts.run_dir.join("checkpoint/g_ema.bpk")).expect("read"),
            "the fine-tuning run starts from the source's EMA generator"
        );
        assert!(ft.run_dir.join("init_from.json").exists());
        // A discriminator of another shape starts fresh instead of failing to load.
        let other = TrainOptions {
            run_dir: dir.path().join("fine-tune-half-resolution-d"),
            ..ft.clone()
        };
        std::fs::create_dir_all(&other.run_dir).expect("mkdir");
        let half_d = ft.config.clone().with_discriminator(
            DiscriminatorConfig::new()
                .with_stem(2)
                .with_channels(vec![4, 8]),
        );
        Trainer::new(&half_d, &other, &data).expect("init from run with another discriminator");
        // Fine-tuning the ray-drop logit alone: a few steps change the second row of the
        // heads and nothing else of the generator.
        let drop_only = TrainOptions {
            run_dir: dir.path().join("fine-tune-drop-head"),
            ..ft.clone()
        };
        std::fs::create_dir_all(&drop_only.run_dir).expect("mkdir");
        let cfg = ft.config.clone().with_drop_head_only(true).with_lr(0.05);
        let mut t = Trainer::new(&cfg, &drop_only, &data).expect("init from run");
        let before = generator_values(&t.g);
        for _ in 0..3 {
            t.step(&data).expect("step");
        }
        let after = generator_values(&t.g);
        let AnyGenerator::Implicit(generator) = &t.g else {
            panic!("dusty2 run")
        };
        let heads: Vec<ParamId> = generator
            .blocks
            .iter()
            .flat_map(|b| [b.head.weight.id, b.head.bias.id])
            .collect();
        let mut drop_rows_moved = false;
        for ((id, a), (_, b)) in before.iter().zip(&after) {
            if !heads.contains(id) {
                assert_eq!(a, b, "a frozen parameter moved");
                continue;
            }
            // [2, d] or [2]: the first half is the depth row, the second the drop logit.
            let half = a.len() / 2;
            assert_eq!(a[..half], b[..half], "the depth output of a head moved");
            drop_rows_moved |= a[half..] != b[half..];
        }
        assert!(drop_rows_moved, "the drop logit did not train");
        // Sampling from the run, on the training grid and on a 2x denser one.
        let mut sopts = crate::model::sample::SampleOptions {
            n: 3,
            seed: 1,
            truncation: 1.0,
            grid: Some(data.angles.clone()),
        };
        let model =
            crate::model::weights::Model::from_dir(&opts.run_dir, &Device::flex()).expect("model");
        let scans = crate::model::sample::sample(&model, &sopts, &Device::flex()).expect("sample");
        assert_eq!(scans.len(), 3);
        let s = &scans[0];
        assert_eq!(s.range_m.len(), h * w);
        assert!(s.drop_prob.iter().all(|p| (0.0..=1.0).contains(p)));
        assert!(s.range_m.iter().zip(&s.mask).all(|(r, m)| (*r > 0.0) == *m));
        assert_eq!(s.points().len(), s.mask.iter().filter(|m| **m).count());
        sopts.grid = Some(crate::model::layers::AngleGridExt::resample(
            &data.angles,
            2 * h,
            2 * w,
        ));
        let dense = crate::model::sample::sample(&model, &sopts, &Device::flex()).expect("dense");
        assert_eq!(dense[0].range_m.len(), 4 * h * w);
        // SWD of the run against the real set, and the real set against itself (floor 0).
        let cfg = crate::model::metrics::SwdConfig {
            patches_per_image: 16,
            projections: 8,
            ..Default::default()
        };
        let report = crate::model::metrics::swd_of_model(&model, &data, 4, &cfg, &Device::flex())
            .expect("swd");
        assert_eq!(report.per_level.len(), 3);
        assert!(report.mean > 0.0 && report.mean.is_finite());
        let floor = crate::model::metrics::swd_between(&data, &data, &cfg);
        assert!(
            floor.mean < report.mean,
            "floor {} run {}",
            floor.mean,
            report.mean
        );
    }

    /// A coarse-to-fine, reconstruction-assisted run grows at its stage boundary (a fresh
    /// discriminator and encoder of the finer grid), and a run stopped right after the growth
    /// and resumed ends with the same weights as one that ran through.
    #[test]
    fn a_staged_assisted_run_grows_and_resumes_as_if_uninterrupted() {
        let dir = tempfile::tempdir().expect("tempdir");
        let cache = synthetic_cache(dir.path(), 8, 5, |i, _| (i % 64) as f32 / 64.0 - 0.5);
        let config = tiny_run_config()
            .with_total_images(10)
            .with_snapshot_every_images(100)
            .with_stages(vec![Stage::new(1, 4)])
            // The first stage's discriminator differs from the full grid's.
            .with_stage_discriminators(vec![
                DiscriminatorConfig::new().with_channels(vec![4, 4, 8]),
            ])
            .with_d_warmup_images(2)
            .with_log_every_steps(1)
            .with_reconstruction(Some(ReconstructionConfig::new()));
        let opts = |name: &str, total: u64| TrainOptions {
            run_dir: dir.path().join(name),
            dataset_cache: cache.clone(),
            scans: vec![],
            config: config.clone(),
            backend: Backend::Flex,
            total_images: Some(total),
            max_duration: None,
            progress: false,
            init_from: None,
        };
        let state = |o: &TrainOptions| -> TrainState {
            let text = std::fs::read_to_string(o.run_dir.join("checkpoint/state.json"));
            serde_json::from_str(&text.expect("state")).expect("json")
        };
        // Weight files carry random parameter ids, so the values are compared.
        let device = Device::flex();
        let weights = |o: &TrainOptions| {
            let ck = o.run_dir.join("checkpoint");
            let (g_ema, _) = load_generator(&o.run_dir, &device).expect("g_ema");
            let d = stage_discriminator(&config, 1, &Level::of(&[], 0, 2, 64, 64), &device)
                .try_load_file(ck.join("d.bpk"))
                .expect("d");
            let level = Level::of(&[], 0, 2, 64, 64);
            let e = InLoopEncoder::new(&ReconstructionConfig::new(), &level, 8, &device)
                .encoder
                .try_load_file(ck.join("e.bpk"))
                .expect("e");
            let state = std::fs::read_to_string(ck.join("state.json")).expect("state");
            (
                module_values(&g_ema),
                module_values(&d),
                module_values(&e),
                state,
            )
        };
        let through = opts("through", 10);
        run(&through).expect("train");
        let stopped = opts("stopped", 4);
        run(&stopped).expect("train to the boundary");
        let at_boundary = state(&stopped);
        assert_eq!((at_boundary.images, at_boundary.stage), (4, 1));
        assert!(stopped.run_dir.join("checkpoint/e.bpk").exists());
        let at_four = weights(&stopped);
        run(&opts("stopped", 10)).expect("resume");
        assert_eq!(state(&through).stage, 1);
        assert!(
            weights(&through) == weights(&stopped),
            "a resumed run ends elsewhere than one that ran through"
        );
        assert!(
            at_four != weights(&stopped),
            "the resumed steps changed nothing"
        );
        // The log shows both grids, and the generator sitting out the warm-up after growing.
        let log = std::fs::read_to_string(through.run_dir.join("log.jsonl")).expect("log");
        let lines: Vec<serde_json::Value> = log
            .lines()
            .map(|l| serde_json::from_str(l).expect("json line"))
            .collect();
        let grids: Vec<&serde_json::Value> = lines.iter().map(|l| &l["grid"]).collect();
        assert_eq!(grids[0], &serde_json::json!([32, 32]));
        assert_eq!(grids[lines.len() - 1], &serde_json::json!([64, 64]));
        let grown = lines.iter().position(|l| l["stage"] == 1).expect("grew");
        assert!(
            lines[grown + 1]["loss_g"].is_null(),
            "the generator waits out the warm-up"
        );
        assert!(lines[grown + 2]["loss_g"].is_number());
        assert!(
            lines
                .iter()
                .all(|l| l["reconstruction"].is_number() || l["loss_g"].is_null())
        );
    }
}
