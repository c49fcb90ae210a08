//! Training the amortised encoder against the frozen generator (`rangegan-mcap train-encoder`).
//!
//! Each step draws generated scans (w known: w = mapping(z); observed through a sampled ray-drop
//! mask) and real KITTI training scans (random azimuth roll). Some observations are made sparse
//! (rows or random points) so the encoder also serves restoration. Loss: on generated scans
//! ||w_hat - w||^2 / d_w, on all scans the auto-decoding reconstruction loss of G(w_hat) against
//! the full observation. Adam; checkpoints with resume like the GAN run.
//!
//! Run directory: `config.json` (written first), `checkpoint/` (encoder, optimiser,
//! state.json; replaced atomically), `export/` (config.json + encoder.bpk, the form shipped in
//! `models/encoder/`), `log.jsonl`.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use burn::config::Config;
use burn::module::Module;
use burn::optim::{AdamConfig, GradientsParams, ModuleOptimizer};
use burn::tensor::Device;
use serde::{Deserialize, Serialize};

use super::Backend;
use super::run_dir::{open_log, read_state};
use super::scans::ScanSource;
use crate::decode::Sparsify;
use crate::decode::amortised::{Encoder, EncoderConfig};
use crate::decode::loss::reconstruction_loss;
use crate::model::AnyGenerator;
use crate::model::data::RangeDataset;
use crate::model::generator::Generator;
use crate::model::measurement::MeasurementConfig;
use crate::model::weights::Model;
use crate::util::rng::Rng;
use crate::util::tensor::{tensor_from, tensor_to_vec};

/// Everything that defines an encoder run; saved as `config.json` before training starts.
#[derive(Config, Debug)]
pub struct EncoderTrainConfig {
    #[config(default = "EncoderConfig::new()")]
    pub encoder: EncoderConfig,
    /// Generated scans per step.
    #[config(default = 4)]
    pub batch_generated: usize,
    /// Real scans per step.
    #[config(default = 4)]
    pub batch_real: usize,
    #[config(default = 1e-3)]
    pub lr: f64,
    /// Weight of ||w_hat - w||^2 / d_w on generated scans.
    #[config(default = 1.0)]
    pub latent_weight: f32,
    /// Weight of the reconstruction loss.
    #[config(default = 1.0)]
    pub rec_weight: f32,
    #[config(default = 2)]
    pub pyramid_levels: usize,
    /// Probability that an observation is made sparse (half rows, half points).
    #[config(default = 0.3)]
    pub sparse_prob: f32,
    #[config(default = 200000)]
    pub total_steps: u64,
    #[config(default = 300)]
    pub checkpoint_every_secs: u64,
    #[config(default = 10)]
    pub log_every_steps: u64,
    #[config(default = 3)]
    pub seed: u64,
}

/// How to run (not saved).
#[derive(Debug, Clone)]
pub struct EncoderTrainOptions {
    pub run_dir: PathBuf,
    pub dataset_cache: PathBuf,
    /// The scans to build the cache from (on the generator's grid); `None`: the cache must
    /// exist.
    pub source: Option<ScanSource>,
    /// Generator directory; `None` = the shipped weights.
    pub model: Option<PathBuf>,
    pub config: EncoderTrainConfig,
    pub total_steps: Option<u64>,
    pub max_duration: Option<Duration>,
    /// Where the encoder trains (the generator is loaded onto the same device).
    pub backend: Backend,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
struct State {
    step: u64,
    rng: Rng,
}

/// Read a run's `config.json`.
pub fn load_config(path: &Path) -> Result<EncoderTrainConfig> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("failed to read '{}'", path.display()))?;
    serde_json::from_str(&text).with_context(|| format!("bad config '{}'", path.display()))
}

/// Train (or resume) an encoder run.
pub fn run(opts: &EncoderTrainOptions) -> Result<()> {
    std::fs::create_dir_all(&opts.run_dir)
        .with_context(|| format!("failed to create '{}'", opts.run_dir.display()))?;
    let inner = opts.backend.device()?;
    let model = Model::load(opts.model.as_deref(), &inner)?;
    let config_path = opts.run_dir.join("config.json");
    let mut config = if config_path.exists() {
        load_config(&config_path)?
    } else {
        // A new encoder reads its generator's grid.
        let mut c = opts.config.clone();
        c.encoder = c
            .encoder
            .with_height(model.config.sensor.beams())
            .with_width(model.config.sensor.columns);
        c
    };
    if let Some(n) = opts.total_steps {
        config.total_steps = n;
    }
    config
        .save(&config_path)
        .with_context(|| format!("failed to write '{}'", config_path.display()))?;
    let data = super::scans::load_dataset(&opts.dataset_cache, opts.source.as_ref())?;
    if data.height != config.encoder.height
        || data.width != config.encoder.width
        || data.depth_range() != model.config.depth_range()
        || data.is_empty()
    {
        bail!(
            "dataset '{}' has {} images of {}x{} ({}, {}-{} m); the encoder expects {}x{} (generator '{}': {}, {}-{} m)",
            opts.dataset_cache.display(),
            data.len(),
            data.height,
            data.width,
            data.profile.name,
            data.profile.min_range_m,
            data.profile.max_range_m,
            config.encoder.height,
            config.encoder.width,
            model.source,
            model.config.sensor.name,
            model.config.sensor.min_range_m,
            model.config.sensor.max_range_m,
        );
    }
    let measurement = model.config.measurement.clone();
    let AnyGenerator::Implicit(generator) = model.generator else {
        bail!("the encoder serves the implicit dusty2 generator only");
    };
    if generator.d_w() != config.encoder.d_w {
        bail!(
            "generator '{}' has w of size {}, the encoder config {}",
            model.source,
            generator.d_w(),
            config.encoder.d_w
        );
    }
    let mut t = Trainer::new(config, generator, measurement, inner, &opts.run_dir, &data)?;
    t.train(opts, &data)
}

struct Trainer {
    config: EncoderTrainConfig,
    inner: Device,
    ad: Device,
    generator: Generator,
    frozen_ad: Generator,
    cache: crate::model::generator::GridCache,
    cache_ad: crate::model::generator::GridCache,
    w_avg: Vec<f32>,
    measurement: MeasurementConfig,
    encoder: Encoder,
    opt: ModuleOptimizer,
    state: State,
}

impl Trainer {
    fn new(
        config: EncoderTrainConfig,
        generator: Generator,
        measurement: MeasurementConfig,
        inner: Device,
        run_dir: &Path,
        data: &RangeDataset,
    ) -> Result<Self> {
        let ad = inner.clone().autodiff();
        let frozen_ad = generator.clone().fork(&ad).no_grad();
        let cache = generator.prepare(&data.angles, &inner);
        let cache_ad = generator.prepare(&data.angles, &ad);
        let w_avg = tensor_to_vec(generator.mapping.w_avg.val());
        let mut encoder = config.encoder.init(&ad);
        let mut opt = AdamConfig::new().with_epsilon(1e-8).init();
        let mut state = State {
            step: 0,
            rng: Rng::new(config.seed),
        };
        let ck = run_dir.join(super::CHECKPOINT);
        if ck.join("state.json").exists() {
            encoder = encoder
                .try_load_file(ck.join("encoder.bpk"))
                .map_err(|e| anyhow::anyhow!("failed to load '{}': {e}", ck.display()))?;
            opt = opt
                .load(ck.join("opt.bpk"))
                .map_err(|e| anyhow::anyhow!("failed to load '{}': {e}", ck.display()))?;
            state = read_state(&ck)?;
        }
        Ok(Trainer {
            config,
            inner,
            ad,
            generator,
            frozen_ad,
            cache,
            cache_ad,
            w_avg,
            measurement,
            encoder,
            opt,
            state,
        })
    }

    fn train(&mut self, opts: &EncoderTrainOptions, data: &RangeDataset) -> Result<()> {
        let started = Instant::now();
        let mut last_ck = Instant::now();
        let mut log = open_log(&opts.run_dir, self.state.step)?;
        let mut window = Vec::new();
        let mut window_start = Instant::now();
        while self.state.step < self.config.total_steps {
            let m = self.step(data)?;
            self.state.step += 1;
            window.push(m);
            if self.state.step.is_multiple_of(self.config.log_every_steps) {
                let n = window.len() as f32;
                let mean = |f: fn(&StepMetrics) -> f32| window.iter().map(f).sum::<f32>() / n;
                let line = serde_json::json!({
                    "step": self.state.step,
                    "loss": mean(|m| m.loss),
                    "latent": mean(|m| m.latent),
                    "rec_generated": mean(|m| m.rec_generated),
                    "rec_real": mean(|m| m.rec_real),
                    "secs_per_step": window_start.elapsed().as_secs_f32() / n,
                });
                writeln!(log, "{line}")?;
                window.clear();
                window_start = Instant::now();
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

    /// Observations `[b, 1, H, W]` (host): generated then real; returns (observed net, observed
    /// mask, loss target net, loss mask, true w of the generated ones).
    fn batch(&mut self, data: &RangeDataset) -> Batch {
        let (h, w) = (data.height, data.width);
        let n = h * w;
        let bg = self.config.batch_generated;
        let br = self.config.batch_real;
        let d_z = self.generator.d_z();
        let mut target = Vec::with_capacity((bg + br) * n);
        let mut mask = Vec::with_capacity((bg + br) * n);
        let mut w_true = Vec::new();
        // Generated depths beyond the valid range are not measurable either.
        let farthest = 2.0 * data.depth_range().x_d_floor() - 1.0;
        if bg > 0 {
            let z = self.state.rng.normal_tensor([bg, d_z], &self.inner);
            let w_gen = self.generator.mapping.forward(z); // [bg, d_w]
            let out = self.generator.render(w_gen.clone(), &self.cache, None);
            let m = self
                .measurement
                .measure(out.x_d.clone(), out.keep_logit, &mut self.state.rng);
            let keep = tensor_to_vec(m.mask);
            let x_d = tensor_to_vec(out.x_d);
            for (x, k) in x_d.iter().zip(&keep) {
                let valid = *k > 0.5 && *x > farthest;
                target.push(if valid { *x } else { -1.0 });
                mask.push(if valid { 1.0 } else { 0.0 });
            }
            w_true = tensor_to_vec(w_gen);
        }
        for _ in 0..br {
            let i = self.state.rng.below(data.len());
            let shift = self.state.rng.below(w);
            let img = data.image(i);
            for r in 0..h {
                for j in 0..w {
                    let v = img[r * w + (j + shift) % w];
                    target.push(v);
                    mask.push(if v > -1.0 { 1.0 } else { 0.0 });
                }
            }
        }
        let mut seen = mask.clone();
        for b in 0..bg + br {
            let u = self.state.rng.uniform();
            let sparse = if u < self.config.sparse_prob * 0.5 {
                Some(Sparsify::Lines([8, 16, 32][self.state.rng.below(3)]))
            } else if u < self.config.sparse_prob {
                Some(Sparsify::Fraction(0.05 + 0.45 * self.state.rng.uniform()))
            } else {
                None
            };
            if let Some(s) = sparse {
                s.apply(&mut seen[b * n..(b + 1) * n], h, w, &mut self.state.rng);
            }
        }
        let observed = target
            .iter()
            .zip(&seen)
            .map(|(t, s)| if *s > 0.0 { *t } else { -1.0 })
            .collect();
        Batch {
            observed,
            seen,
            target,
            mask,
            w_true,
            size: bg + br,
        }
    }

    fn step(&mut self, data: &RangeDataset) -> Result<StepMetrics> {
        let (h, w) = (data.height, data.width);
        let batch = self.batch(data);
        let b = batch.size;
        let bg = self.config.batch_generated;
        let d_w = self.w_avg.len();
        let ad = self.ad.clone();
        let shape = [b, 1, h, w];
        let observed = tensor_from(batch.observed, shape, &ad);
        let seen = tensor_from(batch.seen, shape, &ad);
        let target = tensor_from(batch.target, shape, &ad);
        let mask = tensor_from(batch.mask, shape, &ad);
        let w_avg = tensor_from(self.w_avg.clone(), [1, d_w], &ad);
        let w_hat = self.encoder.forward(observed, seen) + w_avg; // [b, d_w]
        let x_d = self
            .frozen_ad
            .render(w_hat.clone(), &self.cache_ad, None)
            .x_d; // [b, 1, H, W]
        let rec = reconstruction_loss(x_d, target, mask, self.config.pyramid_levels); // [b]
        let rec_host = tensor_to_vec(rec.clone().inner());
        let mut loss = rec.mean().mul_scalar(self.config.rec_weight);
        let mut latent = 0.0;
        if bg > 0 {
            let w_true = tensor_from(batch.w_true, [bg, d_w], &ad);
            let l = (w_hat.narrow(0, 0, bg) - w_true).powi_scalar(2).mean();
            latent = l.clone().inner().into_scalar::<f32>();
            loss = loss + l.mul_scalar(self.config.latent_weight);
        }
        let loss_host = loss.clone().inner().into_scalar::<f32>();
        if !loss_host.is_finite() {
            bail!("encoder loss is {loss_host} at step {}", self.state.step);
        }
        let grads = GradientsParams::from_grads(loss.backward(), &self.encoder);
        self.encoder = self.opt.step(self.config.lr, self.encoder.clone(), grads);
        let mean = |v: &[f32]| {
            if v.is_empty() {
                0.0
            } else {
                v.iter().sum::<f32>() / v.len() as f32
            }
        };
        Ok(StepMetrics {
            loss: loss_host,
            latent,
            rec_generated: mean(&rec_host[..bg.min(b)]),
            rec_real: mean(&rec_host[bg.min(b)..]),
        })
    }

    /// Write the checkpoint to a temp folder and swap it in; refresh `export/`.
    fn checkpoint(&self, run_dir: &Path) -> Result<()> {
        let err = |e: burn::store::RecordError| anyhow::anyhow!("failed to save checkpoint: {e}");
        super::write_checkpoint(run_dir, |tmp| {
            self.encoder
                .clone()
                .save_file(tmp.join("encoder.bpk"))
                .map_err(err)?;
            self.opt.save(tmp.join("opt.bpk")).map_err(err)?;
            std::fs::write(
                tmp.join("state.json"),
                serde_json::to_string_pretty(&self.state)?,
            )?;
            Ok(())
        })?;
        // The shippable form: the encoder's own config + inference weights.
        let export = run_dir.join("export");
        std::fs::create_dir_all(&export)?;
        self.config.encoder.save(export.join("config.json"))?;
        self.encoder
            .valid()
            .save_file(export.join("encoder.bpk"))
            .map_err(err)?;
        Ok(())
    }
}

struct Batch {
    observed: Vec<f32>,
    seen: Vec<f32>,
    target: Vec<f32>,
    mask: Vec<f32>,
    w_true: Vec<f32>,
    size: usize,
}

struct StepMetrics {
    loss: f32,
    latent: f32,
    rec_generated: f32,
    rec_real: f32,
}
