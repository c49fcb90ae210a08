//! The GAN training loop: non-saturating loss, a finite-difference R1 penalty (burn has no
//! double backward), Adam, generator EMA, adaptive augmentation restricted to operations that
//! keep the circular structure, early random pixel dropout, checkpoints with resume, a JSONL
//! loss log, an indicatif bar and PNG snapshots. Entry point: [`run`].
//!
//! Run directory layout: `config.json` (written first), `checkpoint/` (g, g_ema, d, optimiser
//! records, state.json, and on windows with whole-turn steps d_whole and whole.json;
//! replaced atomically), `log.jsonl`, `snapshots/*.png`.
//!
//! One file per part: `start` (a fresh, resumed or fine-tuning start), `step` (one D
//! and G step), `whole` (the whole-turn steps among windows) and `checkpoint`
//! (checkpoints and snapshots).

use std::io::Write;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail, ensure};
use burn::config::Config;
use burn::optim::{AdamConfig, ModuleOptimizer};
use burn::tensor::{Device, Tensor};
use indicatif::{ProgressBar, ProgressStyle};

use crate::model::data::RangeDataset;
use crate::model::discriminator::Discriminator;
use crate::model::generator::{GridCache, random_subgrid_shift};
use crate::model::{AnyGenerator, Arch};
use crate::util::tensor::tensor_from;

use super::config::{TrainConfig, TrainOptions, TrainState, load_config};
use super::growth::{Level, stage_at};
use super::reconstruct::InLoopEncoder;
use super::run_dir::open_log;

mod checkpoint;
mod start;
mod step;
mod whole;

pub use checkpoint::write_png;

use start::{SelfSupervision, in_loop_encoder, stage_self_decoder};
use whole::WholePass;

/// Train (or resume) in `opts.run_dir`.
pub fn run(opts: &TrainOptions) -> Result<()> {
    std::fs::create_dir_all(opts.run_dir.join("snapshots"))
        .with_context(|| format!("failed to create '{}'", opts.run_dir.display()))?;
    let config_path = opts.run_dir.join("config.json");
    let data = super::scans::load_dataset(&opts.dataset_cache, opts.source.as_ref())?;
    let config = if config_path.exists() {
        load_config(&config_path)?
    } else {
        // A new run (fine-tuning included) learns the sensor of its scans.
        let config = opts.config.clone().with_sensor(data.profile.clone());
        config.check_grid(&data)?;
        config
            .save(&config_path)
            .with_context(|| format!("failed to write '{}'", config_path.display()))?;
        config
    };
    // The image budget and the discriminator's regularisers may change on a resumed run.
    let mut changed = config.clone();
    if let Some(n) = opts.total_images {
        changed = changed.with_total_images(n);
    }
    if let Some(r) = &opts.regularisation {
        changed = changed.with_regularisation(r.clone());
    }
    if let Some(share) = opts.sim_share {
        changed = changed.with_sim_share(share);
    }
    changed.check().context("the run's settings")?;
    let config = if serde_json::to_value(&changed)? != serde_json::to_value(&config)? {
        changed
            .save(&config_path)
            .with_context(|| format!("failed to write '{}'", config_path.display()))?;
        changed
    } else {
        config
    };
    config
        .check_grid(&data)
        .with_context(|| format!("dataset '{}'", opts.dataset_cache.display()))?;
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
    let sim = simulated_scans(&opts.run_dir, &config, &data)?;
    let mut trainer = Trainer::new(&config, opts, &data)?;
    trainer.sim = sim;
    trainer.train(opts, &data)
}

/// Where the run mixes simulated scans among the real ones: `RUN_DIR/sim.bin`, on the same
/// grid as the real scans.
fn simulated_scans(
    run_dir: &std::path::Path,
    config: &TrainConfig,
    data: &RangeDataset,
) -> Result<Option<RangeDataset>> {
    if config.sim_share <= 0.0 {
        return Ok(None);
    }
    let path = run_dir.join(SIMULATED_SCANS);
    ensure!(
        path.exists(),
        "the run mixes in simulated scans (share {}) but '{}' is missing (train --sim-mix builds it)",
        config.sim_share,
        path.display()
    );
    let sim = RangeDataset::load(&path)?;
    ensure!(
        (sim.height, sim.width) == (data.height, data.width) && !sim.is_empty(),
        "'{}' holds {} scans of {} x {}; the real scans are {} x {}",
        path.display(),
        sim.len(),
        sim.height,
        sim.width,
        data.height,
        data.width
    );
    Ok(Some(sim))
}

/// The simulated scans a run mixes in, in its run directory.
pub const SIMULATED_SCANS: &str = "sim.bin";

struct Trainer {
    config: TrainConfig,
    device: Device,
    g: AnyGenerator,
    g_ema: AnyGenerator,
    d: Discriminator,
    opt_g: ModuleOptimizer,
    opt_d: ModuleOptimizer,
    /// The discriminator's self-supervised decoder, where the run has one.
    self_decoder: Option<SelfSupervision>,
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
    /// Simulated scans mixed among the real ones (`sim_share`).
    sim: Option<RangeDataset>,
    /// The occasional whole-turn step of a run on windows (`whole_every`).
    whole: Option<WholePass>,
}

impl Trainer {
    /// The grid caches of the current level: its blocks, and on windows the strip of
    /// columns a window is rendered on.
    fn cut_grids(&mut self) {
        let strip = match (&self.g, self.level.window) {
            (AnyGenerator::Implicit(g), Some(window)) => Some(window + 2 * g.window_margin()),
            _ => None,
        };
        let cut = |full: &GridCache| {
            let grid = self.level.grid(full);
            strip.map_or(grid.clone(), |columns| grid.first_columns(columns))
        };
        (self.grid, self.grid_inner) = match &self.full_grid {
            Some((grid, inner)) => (Some(cut(grid)), Some(cut(inner))),
            None => (None, None),
        };
        self.cut_whole_grids();
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
        self.level = Level::of(&self.config.stages, stage, blocks, data.height, data.width)
            .with_window(self.config.window);
        self.d = stage_discriminator(&self.config, stage, &self.level, &self.device);
        self.self_decoder = stage_self_decoder(&self.config, stage, &self.device);
        self.encoder = in_loop_encoder(&self.config, &self.level, &self.device);
        self.opt_d = adam(&self.config);
        self.whole = WholePass::wanted(&self.config, &self.level)
            .then(|| WholePass::fresh(&self.config, stage, &self.level, &self.device));
        self.cut_grids();
        true
    }

    /// Whether the generator sits out this step: a fresh discriminator learns first.
    fn d_warming_up(&self) -> bool {
        (self.state.stage > 0 || self.state.fresh_discriminator)
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
        let mut log = open_log(&opts.run_dir, self.state.step)?;
        let started = Instant::now();
        let mut last_ckpt = Instant::now();
        let mut window = (Instant::now(), self.state.images);
        let mut next_snapshot =
            (self.state.images / cfg.snapshot_every_images + 1) * cfg.snapshot_every_images;
        if self.state.images == 0 {
            self.snapshot(opts, data)?;
        }
        while self.state.images < cfg.total_images {
            let whole_turn = self.whole_turn_due();
            let m = if whole_turn {
                self.whole_turn_step(data)?
            } else {
                self.step(data)?
            };
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
                    "apa_p": self.config.regularisation.apa.then_some(self.state.apa_p),
                    "lecam": self.state.lecam.map(|a| [a.real, a.fake]),
                    "self_supervised": m.self_supervised,
                    "pixel_drop": m.pixel_drop,
                    "images_per_s": ips,
                    "stage": self.state.stage,
                    "reconstruction": m.assisted.map(|a| a.reconstruction),
                    "cycle": m.assisted.map(|a| a.cycle),
                    "prior": m.assisted.map(|a| a.prior),
                    "grid": [
                        self.level.height,
                        if whole_turn { self.level.width } else { self.level.trained_width() }
                    ],
                    "whole_turn": self.whole.as_ref().and_then(|w| w.last.map(|l| l.json(w.counters.ada_p))),
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

    /// A batch of real scans at the level's resolution; on windows, those starting at the
    /// columns of `windows`.
    fn real_batch(
        &mut self,
        data: &RangeDataset,
        windows: Option<&[usize]>,
        device: &Device,
    ) -> Tensor<4> {
        let b = self.config.batch_size;
        let level = self.level;
        let width = level.trained_width();
        let mut v = Vec::with_capacity(b * level.height * width);
        let share = self.config.sim_share;
        for k in 0..b {
            // Draws nothing more from the stream where no simulated scans are mixed in.
            let set = match &self.sim {
                Some(sim) if self.state.rng.uniform() < share => sim,
                _ => data,
            };
            let i = self.state.rng.below(set.len());
            match windows {
                Some(start) => v.extend(level.crop(set.image(i), start[k])),
                None if level.factor == 1 => v.extend_from_slice(set.image(i)),
                None => {
                    let phase = level.random_phase(&mut self.state.rng);
                    v.extend(level.sample(set.image(i), set.width, phase));
                }
            }
        }
        tensor_from(v, [b, 1, level.height, width], device)
    }

    /// The first column of each window of a batch, where the level trains on windows.
    fn window_starts(&mut self) -> Option<Vec<usize>> {
        let width = self.level.width;
        self.level.window.map(|_| {
            (0..self.config.batch_size)
                .map(|_| self.state.rng.below(width))
                .collect()
        })
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
}

#[cfg(test)]
mod tests;

/// A fresh discriminator for `level`'s resolution.
pub(super) fn stage_discriminator(
    config: &TrainConfig,
    stage: usize,
    level: &Level,
    device: &Device,
) -> Discriminator {
    config
        .discriminator_of(stage)
        .clone()
        .with_height(level.height)
        .with_width(level.trained_width())
        .with_azimuth_input(level.window.is_some())
        .init(device)
}

/// The Adam optimiser of the run's networks.
pub(super) fn adam(config: &TrainConfig) -> ModuleOptimizer {
    AdamConfig::new()
        .with_beta_1(config.beta1)
        .with_beta_2(config.beta2)
        .with_epsilon(1e-8)
        .init()
}
