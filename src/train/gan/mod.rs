//! The GAN training loop: non-saturating loss, a finite-difference R1 penalty (burn has no
//! double backward), Adam, generator EMA, adaptive augmentation restricted to operations that
//! keep the circular structure, early random pixel dropout, checkpoints with resume, a JSONL
//! loss log, an indicatif bar and PNG snapshots. Entry point: [`run`].
//!
//! Run directory layout: `config.json` (written first), `checkpoint/` (g, g_ema, d, optimiser
//! records, state.json; replaced atomically), `log.jsonl`, `snapshots/*.png`.

use std::fs::OpenOptions;
use std::io::Write;
use std::path::Path;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail, ensure};
use burn::config::Config;
use burn::module::Module;
use burn::optim::{AdamConfig, GradientsParams, ModuleOptimizer};
use burn::tensor::activation::{sigmoid, softplus};
use burn::tensor::{Device, Tensor};
use indicatif::{ProgressBar, ProgressStyle};
use rayon::prelude::*;

use crate::model::data::{DROPPED, RangeDataset};
use crate::model::discriminator::Discriminator;
use crate::model::generator::{Generator, GridCache, random_subgrid_shift};
use crate::model::measurement::MeasurementConfig;
use crate::model::{AnyGenerator, Arch, Generated};
use crate::util::rng::Rng;
use crate::util::tensor::{tensor_from, tensor_to_vec};

use super::config::{TrainConfig, TrainOptions, TrainState, init_generator, load_config};
use super::growth::{Level, stage_at};
use super::reconstruct::{self, InLoopEncoder, Losses};
use super::run_dir::{CHECKPOINT, write_checkpoint};
use super::update::{augment, drop_head_grads, ema_update, mean_grads};

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
            // A widened run starts without G's Adam state (its shapes changed), and a compact
            // checkpoint (the committed one) may leave out D's: it is rebuilt within a few
            // dozen steps (beta1 = 0), and at 64 x 512 it is most of the bytes.
            if ck.join("opt_g.bpk").exists() {
                opt_g = opt_g
                    .load(ck.join("opt_g.bpk"))
                    .map_err(|e| load_err("opt_g", e))?;
            }
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
                    "prior": m.assisted.map(|a| a.prior),
                    "grid": [self.level.height, self.level.width],
                    "real": m.real.json(),
                    "fake": m.fake.json(),
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
        let d_parts: Vec<(DPart, [BatchStats; 2])> = (0..parts)
            .into_par_iter()
            .map(|k| {
                let mut rng = Rng::new(seeds[k]);
                let z = z.clone().narrow(0, k * n, n);
                let shift = shift.as_ref().map(|s| &s[k * n..(k + 1) * n]);
                let (fake, _) = g_inner.generate(z, self.grid_inner.as_ref(), shift);
                let fake = measure(&cfg.measurement, fake, &mut rng).autodiff();
                let real = real.clone().narrow(0, k * n, n);
                let seen = [BatchStats::of(&real), BatchStats::of(&fake)];
                let fake = view.apply(fake, &mut rng);
                let real = view.apply(real, &mut rng);
                let v = lazy.then(|| rng.normal_tensor(real.dims(), &device));
                (
                    d_part(&self.d, &device, &cfg, r1_gamma, fake, real, v),
                    seen,
                )
            })
            .collect();
        let (d_parts, seen): (Vec<DPart>, Vec<[BatchStats; 2]>) = d_parts.into_iter().unzip();
        let seen = [0, 1].map(|i| BatchStats::mean(seen.iter().map(|s| s[i])));
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
            real: seen[0],
            fake: seen[1],
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
        // Reconstruction-assisted runs encode a batch of real scans as well; the ray-drop
        // anchor reads the same batch's drop rate per row.
        let real = (self.encoder.is_some() || cfg.drop_rate_weight > 0.0)
            .then(|| self.real_batch(data, &device));
        let real_row_drop = real
            .as_ref()
            .filter(|_| cfg.drop_rate_weight > 0.0)
            .map(row_drop_rates);
        let rendering = self.rendering_generator();
        let mut g_parts: Vec<GPart> = (0..parts)
            .into_par_iter()
            .map(|k| {
                let g = rendering.clone().fork(&device);
                let z = z.clone().narrow(0, k * n, n);
                let shift = shift.as_ref().map(|s| &s[k * n..(k + 1) * n]);
                let (fake, w) = g.generate(z, self.grid.as_ref(), shift);
                let anchor = match (&real_row_drop, &fake.keep_logit) {
                    (Some(rows), Some(keep_logit)) => Some(
                        drop_rate_anchor(keep_logit.clone(), rows).mul_scalar(cfg.drop_rate_weight),
                    ),
                    _ => None,
                };
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
                let total = match anchor {
                    Some(anchor) => total + anchor,
                    None => total,
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
            prior: acc.prior + v.prior / k,
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
    /// What D was shown, before augmentation: the real batch and the generated one.
    real: BatchStats,
    fake: BatchStats,
}

/// Summary statistics of a measured batch, logged beside D's outputs so that a generator
/// that fools D by moving a global statistic (the drop share, the mean depth) shows.
#[derive(Debug, Clone, Copy, Default)]
struct BatchStats {
    /// Share of dropped pixels (-1 in network units).
    drop: f32,
    /// Mean and standard deviation of the returns' inverse depth (network units).
    mean: f32,
    std: f32,
}

impl BatchStats {
    fn of(x: &Tensor<4>) -> Self {
        let v = tensor_to_vec(x.clone().inner());
        let returns: Vec<f64> = v
            .iter()
            .filter(|&&x| x > DROPPED)
            .map(|&x| x as f64)
            .collect();
        let n = returns.len().max(1) as f64;
        let mean = returns.iter().sum::<f64>() / n;
        let var = returns.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n;
        BatchStats {
            drop: 1.0 - returns.len() as f32 / v.len().max(1) as f32,
            mean: mean as f32,
            std: var.sqrt() as f32,
        }
    }

    fn mean(all: impl Iterator<Item = BatchStats>) -> Self {
        let (mut sum, mut k) = (BatchStats::default(), 0.0f32);
        for s in all {
            sum.drop += s.drop;
            sum.mean += s.mean;
            sum.std += s.std;
            k += 1.0;
        }
        let k = k.max(1.0);
        BatchStats {
            drop: sum.drop / k,
            mean: sum.mean / k,
            std: sum.std / k,
        }
    }

    fn json(self) -> serde_json::Value {
        serde_json::json!({"drop": self.drop, "mean": self.mean, "std": self.std})
    }
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

/// The drop rate of each row of a measured batch (`[batch, 1, H, W]`, -1 = dropped).
fn row_drop_rates(x: &Tensor<4>) -> Vec<f32> {
    let [b, _, h, w] = x.dims();
    let v = tensor_to_vec(x.clone().inner());
    let per_row = (b * w).max(1) as f32;
    (0..h)
        .map(|r| {
            let dropped = (0..b)
                .flat_map(|i| &v[(i * h + r) * w..][..w])
                .filter(|&&x| x <= DROPPED)
                .count();
            dropped as f32 / per_row
        })
        .collect()
}

/// Mean over rows of the squared difference between the expected drop rate of the generated
/// batch's row (from its keep logits `[batch, 1, H, W]`) and `target` (one rate per row).
fn drop_rate_anchor(keep_logit: Tensor<4>, target: &[f32]) -> Tensor<1> {
    let [_, _, h, _] = keep_logit.dims();
    let device = keep_logit.device();
    let drop = sigmoid(keep_logit).neg().add_scalar(1.0); // [batch, 1, H, W]
    let rows = drop.mean_dim(3).mean_dim(0); // [1, 1, H, 1]
    let target = tensor_from(target.to_vec(), [1, 1, h, 1], &device);
    (rows - target).powi_scalar(2).mean()
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
    let png = crate::util::png::encode_gray(w as u32, (images.len() * (h + 2)) as u32, &pixels)?;
    crate::util::fs::write_atomic(path, &png)
        .with_context(|| format!("failed to write '{}'", path.display()))
}

#[cfg(test)]
mod tests;
