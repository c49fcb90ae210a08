//! The occasional whole-turn step of a run on windows of the turn: every
//! `whole_every`-th step renders whole turns and shows them to a discriminator of whole
//! turns, so that the layout of a turn (where the ground, the walls and the blind spots
//! are) keeps a judge while the windows teach detail at full resolution.
//!
//! The whole-turn discriminator keeps its own optimiser, adaptive augmentation and step
//! count (lazy R1 and ADA's updates fall on its own steps). A branch from a whole-turn run
//! starts it from that run's discriminator and ADA probability: it already tells this
//! generator's turns from real ones.

use std::path::Path;

use anyhow::{Context, Result};
use burn::module::Module;
use burn::optim::ModuleOptimizer;
use burn::tensor::Device;
use serde::{Deserialize, Serialize};

use crate::model::data::RangeDataset;
use crate::model::discriminator::Discriminator;
use crate::model::generator::GridCache;
use crate::train::config::{TrainConfig, TrainState, load_config};
use crate::train::growth::Level;
use crate::train::regularise::LecamAnchors;
use crate::train::run_dir::CHECKPOINT;

use super::Trainer;
use super::step::StepMetrics;
use super::{adam, stage_discriminator};

/// The whole-turn discriminator's weights, Adam state and counters in a checkpoint.
pub(super) const WHOLE_D: &str = "d_whole.bpk";
const WHOLE_D_OPT: &str = "opt_d_whole.bpk";
const WHOLE_STATE: &str = "whole.json";

/// What one discriminator carries from step to step besides its weights.
#[derive(Debug, Clone, Copy, Default, Serialize, Deserialize)]
pub(super) struct DCounters {
    pub(super) step: u64,
    pub(super) ada_p: f32,
    ada_acc: f32,
    ada_count: u64,
    apa_p: f32,
    lecam: Option<LecamAnchors>,
}

impl DCounters {
    /// Trade these counters with the ones in the training state.
    fn swap_with(&mut self, state: &mut TrainState) {
        std::mem::swap(&mut self.step, &mut state.step);
        std::mem::swap(&mut self.ada_p, &mut state.ada_p);
        std::mem::swap(&mut self.ada_acc, &mut state.ada_acc);
        std::mem::swap(&mut self.ada_count, &mut state.ada_count);
        std::mem::swap(&mut self.apa_p, &mut state.apa_p);
        std::mem::swap(&mut self.lecam, &mut state.lecam);
    }
}

/// D's side of the latest whole-turn step, logged beside the windows'.
#[derive(Debug, Clone, Copy)]
pub(super) struct WholeMetrics {
    pub(super) loss_d: f32,
    pub(super) d_real: f32,
    pub(super) d_fake: f32,
}

impl WholeMetrics {
    pub(super) fn json(&self, ada_p: f32) -> serde_json::Value {
        serde_json::json!({
            "loss_d": self.loss_d,
            "d_real": self.d_real,
            "d_fake": self.d_fake,
            "ada_p": ada_p,
        })
    }
}

/// Everything of the whole-turn step that differs from a window step. While a whole-turn
/// step runs these sit in the trainer and the windows' sit here.
pub(super) struct WholePass {
    level: Level,
    pub(super) d: Discriminator,
    opt_d: ModuleOptimizer,
    pub(super) grid: Option<GridCache>,
    grid_inner: Option<GridCache>,
    last_r1: Option<f32>,
    pub(super) counters: DCounters,
    pub(super) last: Option<WholeMetrics>,
}

impl WholePass {
    /// Whether a run at `level` takes whole-turn steps: on windows, with `whole_every`.
    pub(super) fn wanted(config: &TrainConfig, level: &Level) -> bool {
        config.whole_every.is_some() && level.window.is_some()
    }

    /// A fresh whole-turn pass beside the windows of `level`.
    pub(super) fn fresh(
        config: &TrainConfig,
        stage: usize,
        level: &Level,
        device: &Device,
    ) -> Self {
        let whole = level.with_window(None);
        WholePass {
            level: whole,
            d: stage_discriminator(config, stage, &whole, device),
            opt_d: adam(config),
            grid: None,
            grid_inner: None,
            last_r1: None,
            counters: DCounters::default(),
            last: None,
        }
    }

    /// The whole-turn pass of a run on windows at `level`: resumed from the run's checkpoint,
    /// else started from `init_from`'s whole-turn discriminator where it has one of this
    /// shape, else fresh.
    pub(super) fn start(
        config: &TrainConfig,
        stage: usize,
        level: &Level,
        run_dir: &Path,
        init_from: Option<&Path>,
        device: &Device,
    ) -> Result<Self> {
        let mut pass = Self::fresh(config, stage, level, device);
        let own = run_dir.join(CHECKPOINT);
        if own.join(WHOLE_D).exists() {
            pass.load(&own, WHOLE_D)?;
            if own.join(WHOLE_D_OPT).exists() {
                pass.opt_d = pass
                    .opt_d
                    .load(own.join(WHOLE_D_OPT))
                    .map_err(|e| anyhow::anyhow!("failed to load {WHOLE_D_OPT}: {e}"))?;
            }
            let path = own.join(WHOLE_STATE);
            let text = std::fs::read_to_string(&path)
                .with_context(|| format!("failed to read '{}'", path.display()))?;
            pass.counters =
                serde_json::from_str(&text).with_context(|| format!("bad '{}'", path.display()))?;
        } else if let Some(src) = init_from.filter(|_| !own.join("state.json").exists()) {
            pass.start_from(config, &src.join(CHECKPOINT), src)?;
        }
        Ok(pass)
    }

    /// Start from a source run's whole-turn discriminator: a windows run's own whole-turn
    /// one, or a whole-turn run's D (with its ADA probability) where the shapes match.
    fn start_from(&mut self, config: &TrainConfig, ck: &Path, src: &Path) -> Result<()> {
        if ck.join(WHOLE_D).exists() {
            self.load(ck, WHOLE_D)?;
            if let Ok(text) = std::fs::read_to_string(ck.join(WHOLE_STATE)) {
                let counters: DCounters = serde_json::from_str(&text)?;
                self.counters.ada_p = counters.ada_p;
            }
            return Ok(());
        }
        let Ok(source) = load_config(&src.join("config.json")) else {
            return Ok(());
        };
        let same_shape = serde_json::to_value(&source.discriminator)?
            == serde_json::to_value(&config.discriminator)?;
        if source.window.is_none() && same_shape && ck.join("d.bpk").exists() {
            self.load(ck, "d.bpk")?;
            if let Ok(text) = std::fs::read_to_string(ck.join("state.json")) {
                let state: TrainState = serde_json::from_str(&text)?;
                self.counters.ada_p = state.ada_p;
            }
        }
        Ok(())
    }

    fn load(&mut self, ck: &Path, file: &str) -> Result<()> {
        let path = ck.join(file);
        self.d = self
            .d
            .clone()
            .try_load_file(&path)
            .map_err(|e| anyhow::anyhow!("failed to load '{}': {e}", path.display()))?;
        Ok(())
    }

    /// Write the whole-turn discriminator into a checkpoint being assembled in `tmp`.
    pub(super) fn save(&self, tmp: &Path) -> Result<()> {
        self.d
            .clone()
            .save_file(tmp.join(WHOLE_D))
            .map_err(|e| anyhow::anyhow!("failed to save the whole-turn discriminator: {e}"))?;
        self.opt_d
            .save(tmp.join(WHOLE_D_OPT))
            .map_err(|e| anyhow::anyhow!("failed to save its optimiser: {e}"))?;
        std::fs::write(
            tmp.join(WHOLE_STATE),
            serde_json::to_string_pretty(&self.counters)?,
        )?;
        Ok(())
    }
}

impl Trainer {
    /// Whether the step about to run is a whole-turn one.
    pub(super) fn whole_turn_due(&self) -> bool {
        match (self.config.whole_every, &self.whole) {
            (Some(every), Some(_)) => (self.state.step + 1).is_multiple_of(every.max(1) as u64),
            _ => false,
        }
    }

    /// One step on whole turns against the whole-turn discriminator.
    pub(super) fn whole_turn_step(&mut self, data: &RangeDataset) -> Result<StepMetrics> {
        self.swap_whole();
        let m = self.step(data);
        self.state.step += 1;
        self.swap_whole();
        let m = m?;
        if let Some(w) = self.whole.as_mut() {
            w.last = Some(WholeMetrics {
                loss_d: m.loss_d,
                d_real: m.d_real,
                d_fake: m.d_fake,
            });
        }
        Ok(m)
    }

    /// Trade the window step's discriminator, level, grids and counters for the whole
    /// turn's (and back).
    fn swap_whole(&mut self) {
        let Some(w) = self.whole.as_mut() else {
            return;
        };
        std::mem::swap(&mut self.level, &mut w.level);
        std::mem::swap(&mut self.d, &mut w.d);
        std::mem::swap(&mut self.opt_d, &mut w.opt_d);
        std::mem::swap(&mut self.grid, &mut w.grid);
        std::mem::swap(&mut self.grid_inner, &mut w.grid_inner);
        std::mem::swap(&mut self.last_r1, &mut w.last_r1);
        w.counters.swap_with(&mut self.state);
    }

    /// The whole-turn pass's grids: its level's blocks on the whole turn.
    pub(super) fn cut_whole_grids(&mut self) {
        let Some(w) = self.whole.as_mut() else {
            return;
        };
        (w.grid, w.grid_inner) = match &self.full_grid {
            Some((grid, inner)) => (Some(w.level.grid(grid)), Some(w.level.grid(inner))),
            None => (None, None),
        };
    }
}
