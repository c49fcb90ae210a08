//! Training the spatial-latent model (`rangegan-mcap train-spatial RUN_DIR`): encoder and
//! renderer together, by reconstruction of returns the encoder did not see and the ray-drop
//! likelihood of rays it did not see, on real KITTI scans at two resolutions and simulated
//! scans of every sensor family ([`data`]).
//!
//! Run directory: `config.json` (written first), `checkpoint/` (network, optimiser,
//! state.json; replaced atomically, so rerunning resumes), `export/` (the shippable form:
//! `config.json` + `spatial.bpk` of the latest state), `best/` (the same for the state that
//! scored best on the validation recordings), `log.jsonl`.

pub mod data;
pub mod validate;

use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use burn::config::Config;
use burn::module::Module;
use burn::optim::{AdamConfig, GradientsAccumulator, GradientsParams, ModuleOptimizer};
use burn::tensor::activation::relu;
use burn::tensor::{Device, Tensor};
use serde::{Deserialize, Serialize};

use super::Backend;
use super::run_dir::{open_log, read_state, write_checkpoint};
use crate::model::spatial::{OWN_FEATURES, Queries, SpatialConfig, SpatialNet, WEIGHTS};
use crate::util::rng::Rng;
use crate::util::tensor::tensor_from;
use data::{Hiding, Source};

/// Everything that defines a run; saved as `config.json` before training starts.
#[derive(Config, Debug)]
pub struct SpatialTrainConfig {
    #[config(default = "SpatialConfig::new()")]
    pub model: SpatialConfig,
    /// Examples per step (halved for sensors of more than 64 beams).
    #[config(default = 8)]
    pub batch: usize,
    /// Columns per training example.
    #[config(default = 256)]
    pub crop: usize,
    #[config(default = 1e-3)]
    pub lr: f64,
    /// Weight of the reconstruction of hidden returns beside that of seen ones.
    #[config(default = 2.0)]
    pub hidden_weight: f32,
    /// Weight of the ray-drop likelihood.
    #[config(default = 1.0)]
    pub drop_weight: f32,
    /// Share of examples with holes (patches, beams, sectors, object shapes).
    #[config(default = 0.85)]
    pub cut: f32,
    /// Share of those holes that are unknown to the encoder rather than drops.
    #[config(default = 0.4)]
    pub unknown_holes: f32,
    /// Share of a crop's rays rendered and scored per step (the same rays for every example
    /// of a batch): the loss is an unbiased estimate at a fraction of the renderer's cost.
    #[config(default = 0.35)]
    pub query_share: f32,
    /// Share of examples with their ranges scaled ([`Hiding::rescale`]).
    #[config(default = 0.3)]
    pub rescale: f32,
    /// Shares of the three kinds of source: full-resolution KITTI, 512-column KITTI, simulated.
    #[config(default = "[0.35, 0.3, 0.35]")]
    pub shares: [f32; 3],
    /// Simulated scans per sensor.
    #[config(default = 24)]
    pub sim_per_sensor: usize,
    #[config(default = 1000000)]
    pub total_steps: u64,
    #[config(default = 600)]
    pub checkpoint_every_secs: u64,
    #[config(default = 20)]
    pub log_every_steps: u64,
    #[config(default = 1000)]
    pub validate_every_steps: u64,
    #[config(default = 5)]
    pub seed: u64,
}

/// How to run (not saved).
#[derive(Debug, Clone)]
pub struct SpatialTrainOptions {
    pub run_dir: PathBuf,
    /// The `real_lidar` folder: KITTI full resolution and every-fourth-point drives.
    pub real_lidar: PathBuf,
    pub config: SpatialTrainConfig,
    pub total_steps: Option<u64>,
    pub max_duration: Option<Duration>,
    pub backend: Backend,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
struct State {
    step: u64,
    rng: Rng,
    /// Examples trained on so far.
    examples: u64,
    /// The best validation score so far (lower is better) and its step.
    best: Option<(f64, u64)>,
}

/// Train (or resume) a run.
pub fn run(opts: &SpatialTrainOptions) -> Result<()> {
    std::fs::create_dir_all(&opts.run_dir)
        .with_context(|| format!("failed to create '{}'", opts.run_dir.display()))?;
    let config_path = opts.run_dir.join("config.json");
    let mut config = if config_path.exists() {
        // A run saved before a setting existed takes that setting's default.
        let text = std::fs::read_to_string(&config_path)
            .with_context(|| format!("failed to read '{}'", config_path.display()))?;
        let saved: serde_json::Value = serde_json::from_str(&text)
            .with_context(|| format!("bad '{}'", config_path.display()))?;
        let mut value = serde_json::to_value(SpatialTrainConfig::new())?;
        crate::util::json::merge(&mut value, saved);
        serde_json::from_value(value).with_context(|| format!("bad '{}'", config_path.display()))?
    } else {
        opts.config.clone()
    };
    if let Some(n) = opts.total_steps {
        config.total_steps = n;
    }
    config
        .save(&config_path)
        .with_context(|| format!("failed to write '{}'", config_path.display()))?;
    let sources = Sources::load(&opts.real_lidar, &config)?;
    let mut t = Trainer::new(config, opts.backend.device()?, &opts.run_dir)?;
    t.train(opts, &sources)
}

/// The training and validation scans.
pub struct Sources {
    fullres: Source,
    kitti: Source,
    sim: Vec<Source>,
    pub validation: Vec<Source>,
}

impl Sources {
    fn load(real_lidar: &Path, config: &SpatialTrainConfig) -> Result<Self> {
        let (fullres, fullres_val) = data::fullres_sources(real_lidar)?;
        let (kitti, kitti_val) = data::kitti_512_sources(real_lidar)?;
        let sim = data::simulated_sources(config.sim_per_sensor, config.seed)?;
        Ok(Sources {
            fullres,
            kitti,
            sim,
            validation: vec![fullres_val, kitti_val],
        })
    }

    fn pick(&self, shares: [f32; 3], rng: &mut Rng) -> &Source {
        let total: f32 = shares.iter().sum();
        let u = rng.uniform() * total;
        if u < shares[0] {
            &self.fullres
        } else if u < shares[0] + shares[1] || self.sim.is_empty() {
            &self.kitti
        } else {
            &self.sim[rng.below(self.sim.len())]
        }
    }
}

struct Trainer {
    config: SpatialTrainConfig,
    ad: Device,
    net: SpatialNet,
    opt: ModuleOptimizer,
    state: State,
}

struct StepMetrics {
    seen: f32,
    hidden: f32,
    drop_nll: f32,
}

impl Trainer {
    fn new(config: SpatialTrainConfig, inner: Device, run_dir: &Path) -> Result<Self> {
        let ad = inner.clone().autodiff();
        let mut rng = Rng::new(config.seed);
        let mut net = config.model.init(&mut rng, &ad);
        let mut opt = AdamConfig::new()
            .with_grad_clipping(Some(
                burn::optim::grad_clipping::GradientClippingConfig::Norm(1.0),
            ))
            .init();
        let mut state = State {
            step: 0,
            rng,
            examples: 0,
            best: None,
        };
        let ck = run_dir.join(super::CHECKPOINT);
        if ck.join("state.json").exists() {
            net = net
                .try_load_file(ck.join(WEIGHTS))
                .map_err(|e| anyhow::anyhow!("failed to load '{}': {e}", ck.display()))?;
            opt = opt
                .load(ck.join("opt.bpk"))
                .map_err(|e| anyhow::anyhow!("failed to load '{}': {e}", ck.display()))?;
            state = read_state(&ck)?;
        }
        Ok(Trainer {
            config,
            ad,
            net,
            opt,
            state,
        })
    }

    fn train(&mut self, opts: &SpatialTrainOptions, sources: &Sources) -> Result<()> {
        let started = Instant::now();
        let mut last_ck = Instant::now();
        let mut log = open_log(&opts.run_dir, self.state.step)?;
        let mut window: Vec<StepMetrics> = Vec::new();
        let mut window_start = Instant::now();
        while self.state.step < self.config.total_steps {
            let m = self.step(sources)?;
            self.state.step += 1;
            window.push(m);
            if self.state.step.is_multiple_of(self.config.log_every_steps) {
                let n = window.len() as f32;
                let mean = |f: fn(&StepMetrics) -> f32| window.iter().map(f).sum::<f32>() / n;
                let line = serde_json::json!({
                    "step": self.state.step,
                    "examples": self.state.examples,
                    "seen_rel_l1": mean(|m| m.seen),
                    "hidden_rel_l1": mean(|m| m.hidden),
                    "drop_nll": mean(|m| m.drop_nll),
                    "secs_per_step": window_start.elapsed().as_secs_f32() / n,
                });
                writeln!(log, "{line}")?;
                window.clear();
                window_start = Instant::now();
            }
            if self
                .state
                .step
                .is_multiple_of(self.config.validate_every_steps)
            {
                self.validate(opts, sources, &mut log)?;
            }
            let out_of_time = opts.max_duration.is_some_and(|d| started.elapsed() >= d);
            if last_ck.elapsed().as_secs() >= self.config.checkpoint_every_secs || out_of_time {
                self.checkpoint(&opts.run_dir)?;
                last_ck = Instant::now();
            }
            if out_of_time {
                return Ok(());
            }
        }
        self.checkpoint(&opts.run_dir)
    }

    /// One optimiser step. The batch is split in two halves whose forward and backward
    /// passes run on two threads (the convolutions' backward is single-threaded), and their
    /// gradients are summed.
    fn step(&mut self, sources: &Sources) -> Result<StepMetrics> {
        let source = sources.pick(self.config.shares, &mut self.state.rng);
        let size = if source.angles.height > 64 {
            self.config.batch.div_ceil(2)
        } else {
            self.config.batch
        };
        let hiding = Hiding {
            cut: self.config.cut,
            unknown_holes: self.config.unknown_holes,
            query_share: self.config.query_share,
            rescale: self.config.rescale,
        };
        let halves = [size.div_ceil(2), size / 2];
        let batches = halves
            .iter()
            .filter(|&&n| n > 0)
            .map(|&n| {
                data::batch(
                    source,
                    n,
                    self.config.crop,
                    &self.config.model,
                    hiding,
                    &mut self.state.rng,
                )
            })
            .collect::<Result<Vec<_>>>()?;
        let parts = batches.len() as f32;
        let results: Vec<(GradientsParams, [f32; 4])> = std::thread::scope(|scope| {
            let handles: Vec<_> = batches
                .into_iter()
                .map(|b| {
                    let net = self.net.clone();
                    let config = &self.config;
                    let ad = self.ad.clone();
                    scope.spawn(move || half_step(&net, config, b, parts, &ad))
                })
                .collect();
            handles
                .into_iter()
                .map(|h| h.join().expect("a half step panicked"))
                .collect()
        });
        let mut acc = GradientsAccumulator::new();
        let mut m = [0.0f32; 4];
        for (grads, v) in results {
            acc.accumulate(&self.net, grads);
            for (a, b) in m.iter_mut().zip(v) {
                *a += b / parts;
            }
        }
        if !m[0].is_finite() {
            bail!("loss is {} at step {}", m[0], self.state.step);
        }
        self.net = self.opt.step(self.config.lr, self.net.clone(), acc.grads());
        self.state.examples += size as u64;
        Ok(StepMetrics {
            seen: m[1],
            hidden: m[2],
            drop_nll: m[3],
        })
    }

    fn validate(
        &mut self,
        opts: &SpatialTrainOptions,
        sources: &Sources,
        log: &mut std::fs::File,
    ) -> Result<()> {
        let net = self.net.valid();
        let scores = validate::score(&net, &self.config.model, &sources.validation);
        let total = validate::selection_score(&scores);
        let line = serde_json::json!({
            "validation": { "step": self.state.step, "score": total, "sources": scores },
        });
        writeln!(log, "{line}")?;
        if self.state.best.is_none_or(|(b, _)| total < b) {
            self.state.best = Some((total, self.state.step));
            export(&net, &self.config.model, &opts.run_dir.join("best"))?;
        }
        Ok(())
    }

    /// Write the checkpoint to a temp folder and swap it in; refresh `export/`.
    fn checkpoint(&self, run_dir: &Path) -> Result<()> {
        let err = |e: burn::store::RecordError| anyhow::anyhow!("failed to save checkpoint: {e}");
        write_checkpoint(run_dir, |tmp| {
            self.net.clone().save_file(tmp.join(WEIGHTS)).map_err(err)?;
            self.opt.save(tmp.join("opt.bpk")).map_err(err)?;
            std::fs::write(
                tmp.join("state.json"),
                serde_json::to_string_pretty(&self.state)?,
            )?;
            Ok(())
        })?;
        export(
            &self.net.valid(),
            &self.config.model,
            &run_dir.join("export"),
        )
    }
}

/// Forward and backward of one part of a batch, its loss scaled by `1 / parts`: the
/// gradients and the (loss, seen, hidden, drop) values.
fn half_step(
    net: &SpatialNet,
    config: &SpatialTrainConfig,
    b: data::Batch,
    parts: f32,
    ad: &Device,
) -> (GradientsParams, [f32; 4]) {
    let latent = net.encode(b.inputs, b.size, b.input_shape, b.circular, ad);
    let [hp, wp] = b.input_shape;
    let queries = Queries::new(
        &b.queries,
        (hp / 2, wp / 2),
        b.circular,
        &config.model.renderer,
        ad,
    );
    let own = tensor_from(b.own_rays, [b.size, queries.len, OWN_FEATURES], ad);
    let shape = [b.size, queries.len];
    let t = |v: Vec<f32>| tensor_from(v, shape, ad);
    let out = net.render(latent, &queries, own, t(b.base));
    let err = (out.log_depth - t(b.log_range)).abs();
    let seen = masked_mean(err.clone(), t(b.seen_return));
    let hidden = masked_mean(err, t(b.hidden_return));
    // -log p(mask) under keep = sigmoid(logit): softplus(l) - y l, written stably.
    let l = out.keep_logit;
    let nll =
        relu(l.clone()) - l.clone() * t(b.returned) + l.abs().neg().exp().add_scalar(1.0).log();
    let drop_nll = masked_mean(nll, t(b.unknown));
    let loss = seen.clone()
        + hidden.clone().mul_scalar(config.hidden_weight)
        + drop_nll.clone().mul_scalar(config.drop_weight);
    let host = |x: &Tensor<1>| x.clone().inner().into_scalar::<f32>();
    let values = [host(&loss), host(&seen), host(&hidden), host(&drop_nll)];
    let grads = GradientsParams::from_grads(loss.div_scalar(parts).backward(), net);
    (grads, values)
}

/// Writes the shippable form of a model (`config.json`, `spatial.bpk`) into `dir`.
pub fn export(net: &SpatialNet, config: &SpatialConfig, dir: &Path) -> Result<()> {
    let tmp = dir.with_extension("tmp");
    let _ = std::fs::remove_dir_all(&tmp);
    std::fs::create_dir_all(&tmp)?;
    config.save(tmp.join("config.json"))?;
    net.clone()
        .save_file(tmp.join(WEIGHTS))
        .map_err(|e| anyhow::anyhow!("failed to save '{}': {e}", tmp.display()))?;
    let _ = std::fs::remove_dir_all(dir);
    std::fs::rename(&tmp, dir).with_context(|| format!("failed to write '{}'", dir.display()))?;
    Ok(())
}

/// Mean of `x` where `mask` is 1 (0 when nothing is masked in).
fn masked_mean(x: Tensor<2>, mask: Tensor<2>) -> Tensor<1> {
    let count = mask.clone().sum().add_scalar(1e-6);
    (x * mask).sum() / count
}
