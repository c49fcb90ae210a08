//! A trainer's start: fresh, resumed from its own checkpoint, or from another run's
//! weights (fine-tuning), with the discriminator and in-loop encoder of its stage.

use std::path::Path;

use anyhow::{Result, bail};
use burn::module::Module;
use burn::optim::{AdamConfig, ModuleOptimizer};
use burn::tensor::Device;

use crate::model::data::RangeDataset;
use crate::model::discriminator::Discriminator;
use crate::model::self_decoder::{SelfDecoder, SelfDecoderConfig};
use crate::model::{AnyGenerator, Arch};
use crate::util::rng::Rng;

use super::whole::WholePass;
use super::{Trainer, adam, stage_discriminator};
use crate::train::config::{TrainConfig, TrainOptions, TrainState, init_generator, load_config};
use crate::train::growth::Level;
use crate::train::reconstruct::InLoopEncoder;
use crate::train::run_dir::{CHECKPOINT, read_state};

impl Trainer {
    pub(super) fn new(
        config: &TrainConfig,
        opts: &TrainOptions,
        data: &RangeDataset,
    ) -> Result<Self> {
        let inner = opts.backend.device()?;
        let device = inner.clone().autodiff();
        let mut g = init_generator(config, &device);
        let mut g_ema = init_generator(config, &inner);
        let mut opt_g = adam(config);
        let mut opt_d = adam(config);
        let ck = opts.run_dir.join(CHECKPOINT);
        let resumed = ck.join("state.json").exists();
        let state = if resumed {
            read_state(&ck)?
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
                lecam: None,
                apa_p: 0.0,
                fresh_discriminator: false,
            }
        };
        let level = Level::of(
            &config.stages,
            state.stage,
            config.generator.channels.len(),
            data.height,
            data.width,
        )
        .with_window(config.window);
        let mut state = state;
        let mut d = stage_discriminator(config, state.stage, &level, &device);
        let mut self_decoder = stage_self_decoder(config, state.stage, &device);
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
            // A run branched with a self-supervised discriminator starts its decoder fresh.
            if let Some(s) = self_decoder
                .as_mut()
                .filter(|_| ck.join(SELF_DECODER).exists())
            {
                s.decoder = s
                    .decoder
                    .clone()
                    .try_load_file(ck.join(SELF_DECODER))
                    .map_err(|e| load_err("the self-supervised decoder", e))?;
                s.opt = std::mem::replace(&mut s.opt, AdamConfig::new().init())
                    .load(ck.join(SELF_DECODER_OPT))
                    .map_err(|e| load_err("the self-supervised decoder's optimiser", e))?;
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
            // A discriminator of another shape than the source's starts fresh, and learns
            // alone for a while before the trained generator takes its gradients.
            let source = load_config(&src.join("config.json")).ok();
            let same_shape = |c: &TrainConfig| {
                serde_json::to_value(&c.discriminator).ok()
                    == serde_json::to_value(&config.discriminator).ok()
            };
            let same_d = level.factor == 1
                && (source.as_ref()).is_some_and(|c| c.window == config.window && same_shape(c));
            state.fresh_discriminator = !same_d;
            (g, g_ema, d) = init_from(src, g, g_ema, d, same_d, config.drop_head_only)?;
            // Windows branched from a whole-turn run: D starts from the source's, which
            // already tells this generator's scans from real ones.
            let whole_d = src.join(CHECKPOINT).join("d.bpk");
            if level.window.is_some()
                && whole_d.exists()
                && (source.as_ref()).is_some_and(|c| c.window.is_none() && same_shape(c))
            {
                let whole = stage_discriminator(config, 0, &level.with_window(None), &device)
                    .try_load_file(&whole_d)
                    .map_err(|e| anyhow::anyhow!("failed to load '{}': {e}", whole_d.display()))?;
                let d_config = &config.discriminator;
                let fold = d_config.stem.max(1) << (d_config.channels.len() - 1);
                d = whole.into_windows(d, level.height / fold);
            }
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
        let whole = WholePass::wanted(config, &level)
            .then(|| {
                let src = opts.init_from.as_deref();
                WholePass::start(config, state.stage, &level, &opts.run_dir, src, &device)
            })
            .transpose()?;
        let snapshot_z = Rng::new(config.seed ^ 0x5eed).normal_tensor([4, g.d_z()], &inner);
        let mut trainer = Self {
            config: config.clone(),
            device,
            g,
            g_ema,
            d,
            opt_g,
            opt_d,
            self_decoder,
            state,
            full_grid,
            grid: None,
            grid_inner: None,
            level,
            encoder,
            snapshot_z,
            last_r1: None,
            sim: None,
            whole,
        };
        trainer.cut_grids();
        Ok(trainer)
    }
}

/// The self-supervised decoder's weights and Adam state in a checkpoint.
pub(super) const SELF_DECODER: &str = "d_decoder.bpk";
pub(super) const SELF_DECODER_OPT: &str = "opt_d_decoder.bpk";

/// The discriminator's self-supervised decoder and its optimiser.
pub(super) struct SelfSupervision {
    pub(super) decoder: SelfDecoder,
    pub(super) opt: ModuleOptimizer,
}

/// A fresh self-supervised decoder for the discriminator of `stage`, where the run has one.
pub(super) fn stage_self_decoder(
    config: &TrainConfig,
    stage: usize,
    device: &Device,
) -> Option<SelfSupervision> {
    (config.regularisation.self_supervised > 0.0).then(|| {
        let d = config.discriminator_of(stage);
        let fold = d.stem.max(1) << (d.channels.len() - 1);
        let last = d.channels[d.channels.len() - 1];
        SelfSupervision {
            decoder: SelfDecoderConfig::for_discriminator(last, fold).init(device),
            opt: adam(config),
        }
    })
}

/// The in-loop encoder for `level` where the run is reconstruction-assisted.
pub(super) fn in_loop_encoder(
    config: &TrainConfig,
    level: &Level,
    device: &Device,
) -> Option<InLoopEncoder> {
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
