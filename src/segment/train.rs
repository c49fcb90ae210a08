//! Training the segmentation network (`rangegan-mcap segment train`): weighted cross-entropy
//! on labelled returns (dropped rays carry no class), Adam with a cosine learning-rate decay
//! over a fixed step budget, random azimuth crops, rolls and mirrors; checkpoints with
//! resume like the GAN run.
//!
//! Run directory: `config.json` (written first), `checkpoint/` (network, optimiser,
//! state.json; replaced atomically), `log.jsonl`, and `model/` (the exported model folder,
//! rewritten at every checkpoint).

use std::fs::OpenOptions;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use burn::config::Config;
use burn::module::Module;
use burn::optim::{AdamConfig, GradientsParams, ModuleOptimizer};
use burn::tensor::activation::log_softmax;
use burn::tensor::{Device, Tensor};
use serde::{Deserialize, Serialize};

use super::classes::{CLASSES, IGNORE, NUM_CLASSES};
use super::data::{CHANNELS, SegDataset, batch, benchmark_profile};
use super::net::{SegNet, SegNetConfig};
use super::{SegModel, SegModelInfo};
use crate::train::{CHECKPOINT, write_checkpoint};
use crate::util::rng::Rng;
use crate::util::tensor::tensor_from;

/// Everything that defines a run; saved as `config.json` before training starts.
#[derive(Config, Debug)]
pub struct SegTrainConfig {
    #[config(default = "SegNetConfig::new()")]
    pub net: SegNetConfig,
    #[config(default = 8)]
    pub batch_size: usize,
    /// Columns of each training crop (128 of 512: a 90-degree view, like the paper's frontal
    /// KITTI images); whole revolutions are used at evaluation.
    #[config(default = 128)]
    pub crop_width: usize,
    /// Peak learning rate (Adam), decayed to 0 by a cosine over `total_steps`.
    #[config(default = 0.002)]
    pub lr: f64,
    #[config(default = 2000)]
    pub total_steps: u64,
    #[config(default = 0)]
    pub seed: u64,
    #[config(default = 120)]
    pub checkpoint_every_secs: u64,
    #[config(default = 20)]
    pub log_every_steps: u64,
}

/// How to run (not saved).
#[derive(Debug, Clone)]
pub struct SegTrainOptions {
    pub run_dir: PathBuf,
    pub recordings: Vec<PathBuf>,
    pub topic: Option<String>,
    /// Used when the run directory has no config.json yet; otherwise the saved one wins.
    pub config: SegTrainConfig,
    /// Stop (with a checkpoint) after this long; a later call resumes.
    pub max_duration: Option<Duration>,
    pub progress: bool,
}

/// Saved with each checkpoint.
#[derive(Debug, Clone, Serialize, Deserialize)]
struct SegTrainState {
    step: u64,
    rng: Rng,
}

/// How a call ended.
#[derive(Debug, Clone, Serialize)]
pub struct SegTrainSummary {
    pub steps: u64,
    pub total_steps: u64,
    pub finished: bool,
    pub scans: usize,
    pub seconds: f64,
    pub model_dir: PathBuf,
}

/// Trains (or resumes) the run in `opts.run_dir`.
pub fn run(opts: &SegTrainOptions) -> Result<SegTrainSummary> {
    std::fs::create_dir_all(&opts.run_dir)
        .with_context(|| format!("cannot create {}", opts.run_dir.display()))?;
    let config_path = opts.run_dir.join("config.json");
    let config = if config_path.exists() {
        SegTrainConfig::load(&config_path)
            .map_err(|e| anyhow::anyhow!("{}: {e}", config_path.display()))?
    } else {
        opts.config
            .save(&config_path)
            .with_context(|| format!("cannot write {}", config_path.display()))?;
        opts.config.clone()
    };
    let profile = benchmark_profile();
    let data = SegDataset::from_recordings(&opts.recordings, opts.topic.as_deref(), &profile)?;
    let m = config.net.multiple();
    if data.height % m != 0 || config.crop_width % m != 0 || config.crop_width > data.width {
        bail!(
            "the network needs image sides divisible by {m} and a crop of at most {} columns \
             (grid {}x{}, crop {})",
            data.width,
            data.height,
            data.width,
            config.crop_width
        );
    }
    let mut trainer = Trainer::new(&config, &opts.run_dir, &data)?;
    let started = Instant::now();
    trainer.train(opts, &data, started)?;
    let info = SegModelInfo {
        net: config.net.clone(),
        classes: CLASSES.iter().map(|s| s.to_string()).collect(),
        profile,
        trained_on: file_names(&opts.recordings),
        steps: trainer.state.step,
        seed: config.seed,
    };
    let model_dir = opts.run_dir.join("model");
    SegModel::save(&info, &trainer.net.valid(), &model_dir)?;
    Ok(SegTrainSummary {
        steps: trainer.state.step,
        total_steps: config.total_steps,
        finished: trainer.state.step >= config.total_steps,
        scans: data.len(),
        seconds: started.elapsed().as_secs_f64(),
        model_dir,
    })
}

fn file_names(paths: &[PathBuf]) -> Vec<String> {
    paths
        .iter()
        .map(|p| {
            p.file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_else(|| p.display().to_string())
        })
        .collect()
}

struct Trainer {
    config: SegTrainConfig,
    device: Device,
    net: SegNet,
    opt: ModuleOptimizer,
    state: SegTrainState,
    weights: [f32; NUM_CLASSES],
}

impl Trainer {
    fn new(config: &SegTrainConfig, run_dir: &Path, data: &SegDataset) -> Result<Self> {
        crate::model::tune_allocator();
        let device = Device::flex().autodiff();
        let mut rng = Rng::new(config.seed);
        let mut net = config.net.init(&mut rng, &device);
        let mut opt = AdamConfig::new().init();
        let mut state = SegTrainState { step: 0, rng };
        let ck = run_dir.join(CHECKPOINT);
        if ck.join("state.json").exists() {
            let err = |what: &str, e: burn::store::RecordError| {
                anyhow::anyhow!("failed to load {what} from '{}': {e}", ck.display())
            };
            net = net
                .try_load_file(ck.join("net.bpk"))
                .map_err(|e| err("the network", e))?;
            opt = opt
                .load(ck.join("opt.bpk"))
                .map_err(|e| err("the optimiser", e))?;
            let text = std::fs::read_to_string(ck.join("state.json"))?;
            state = serde_json::from_str(&text).context("bad checkpoint/state.json")?;
        }
        Ok(Trainer {
            config: config.clone(),
            device,
            net,
            opt,
            state,
            weights: data.class_weights(),
        })
    }

    fn lr(&self) -> f64 {
        let t = self.state.step as f64 / self.config.total_steps.max(1) as f64;
        self.config.lr * 0.5 * (1.0 + (std::f64::consts::PI * t.min(1.0)).cos())
    }

    fn train(&mut self, opts: &SegTrainOptions, data: &SegDataset, started: Instant) -> Result<()> {
        let total = self.config.total_steps;
        let bar = if opts.progress {
            indicatif::ProgressBar::new(total)
        } else {
            indicatif::ProgressBar::hidden()
        };
        bar.set_style(
            indicatif::ProgressStyle::with_template(
                "{elapsed_precise} [{bar:30}] {pos}/{len} steps {msg}",
            )
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
        );
        bar.set_position(self.state.step);
        let log_path = opts.run_dir.join("log.jsonl");
        let mut log = OpenOptions::new()
            .create(true)
            .append(true)
            .open(&log_path)
            .with_context(|| format!("cannot open {}", log_path.display()))?;
        let mut last_ckpt = Instant::now();
        let mut window = (Instant::now(), self.state.step, 0.0f64);
        while self.state.step < total {
            let loss = self.step(data);
            self.state.step += 1;
            window.2 += loss as f64;
            bar.set_position(self.state.step);
            if self.state.step.is_multiple_of(self.config.log_every_steps) {
                let steps = (self.state.step - window.1) as f64;
                let scans_per_s = steps * self.config.batch_size as f64
                    / window.0.elapsed().as_secs_f64().max(1e-9);
                let mean_loss = window.2 / steps;
                window = (Instant::now(), self.state.step, 0.0);
                bar.set_message(format!("loss {mean_loss:.3}  {scans_per_s:.1} crops/s"));
                let line = serde_json::json!({
                    "step": self.state.step,
                    "loss": mean_loss,
                    "lr": self.lr(),
                    "crops_per_s": scans_per_s,
                    "elapsed_s": started.elapsed().as_secs_f64(),
                });
                writeln!(log, "{line}")?;
            }
            if last_ckpt.elapsed() >= Duration::from_secs(self.config.checkpoint_every_secs) {
                self.checkpoint(&opts.run_dir)?;
                last_ckpt = Instant::now();
            }
            if opts.max_duration.is_some_and(|t| started.elapsed() >= t) {
                break;
            }
        }
        self.checkpoint(&opts.run_dir)?;
        bar.finish_and_clear();
        Ok(())
    }

    /// One Adam step; returns the loss.
    fn step(&mut self, data: &SegDataset) -> f32 {
        let (b, cw, h) = (self.config.batch_size, self.config.crop_width, data.height);
        let (input, target) = batch(data, b, cw, &mut self.state.rng);
        let x = tensor_from(input, [b, CHANNELS, h, cw], &self.device);
        let (weights, norm) = weighted_one_hot(&target, b, h, cw, &self.weights);
        let weights = tensor_from(weights, [b, NUM_CLASSES, h, cw], &self.device);
        let logits = self.net.forward(x, false);
        let loss = weighted_cross_entropy(logits, weights, norm);
        let value = loss.clone().into_scalar::<f32>();
        let grads = GradientsParams::from_grads(loss.backward(), &self.net);
        self.net = self.opt.step(self.lr(), self.net.clone(), grads);
        value
    }

    fn checkpoint(&self, run_dir: &Path) -> Result<()> {
        write_checkpoint(run_dir, |tmp| {
            let err = |what: &str, e: burn::store::RecordError| {
                anyhow::anyhow!("failed to save {what}: {e}")
            };
            self.net
                .clone()
                .save_file(tmp.join("net.bpk"))
                .map_err(|e| err("the network", e))?;
            self.opt
                .save(tmp.join("opt.bpk"))
                .map_err(|e| err("the optimiser", e))?;
            std::fs::write(
                tmp.join("state.json"),
                serde_json::to_string_pretty(&self.state)?,
            )?;
            Ok(())
        })
    }
}

/// Per-pixel targets `[b, H, W]` as class weight at the true class and 0 elsewhere
/// (`[b, classes, H, W]`), and the sum of the weights (the loss's normaliser).
fn weighted_one_hot(
    target: &[u8],
    b: usize,
    h: usize,
    w: usize,
    class_weight: &[f32; NUM_CLASSES],
) -> (Vec<f32>, f32) {
    let n = h * w;
    let mut out = vec![0.0f32; b * NUM_CLASSES * n];
    let mut norm = 0.0f32;
    for (idx, &t) in target.iter().enumerate() {
        if t == IGNORE {
            continue;
        }
        let (s, k) = (idx / n, idx % n);
        let wt = class_weight[t as usize];
        out[(s * NUM_CLASSES + t as usize) * n + k] = wt;
        norm += wt;
    }
    (out, norm.max(1e-6))
}

/// Cross-entropy weighted per pixel: -sum(weights * log_softmax(logits)) / norm.
fn weighted_cross_entropy(logits: Tensor<4>, weights: Tensor<4>, norm: f32) -> Tensor<1> {
    log_softmax(logits, 1).mul(weights).sum().div_scalar(-norm)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cross_entropy_matches_the_formula_and_skips_ignored_pixels() {
        let device = Device::flex();
        // One image, 1x2 pixels: pixel 0 is class 2, pixel 1 is ignored.
        let mut w = [1.0f32; NUM_CLASSES];
        w[2] = 3.0;
        let (weights, norm) = weighted_one_hot(&[2, IGNORE], 1, 1, 2, &w);
        assert_eq!(norm, 3.0);
        let logits: Vec<f32> = (0..NUM_CLASSES * 2)
            .map(|i| (i as f32 * 0.37).sin())
            .collect();
        let expected = {
            let l: Vec<f32> = (0..NUM_CLASSES).map(|c| logits[c * 2]).collect();
            let lse = l.iter().map(|v| v.exp()).sum::<f32>().ln();
            lse - l[2]
        };
        let loss = weighted_cross_entropy(
            tensor_from(logits, [1, NUM_CLASSES, 1, 2], &device),
            tensor_from(weights, [1, NUM_CLASSES, 1, 2], &device),
            norm,
        )
        .into_scalar::<f32>();
        assert!((loss - expected).abs() < 1e-5, "{loss} vs {expected}");
    }
}
