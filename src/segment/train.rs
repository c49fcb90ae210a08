//! Training the segmentation network (`rangegan-mcap segment train`): weighted cross-entropy
//! plus Lovász-softmax on labelled returns (dropped rays carry no class), Adam with a cosine
//! learning-rate decay over a step budget, random and class-balanced azimuth crops, rolls and
//! mirrors (and, for small real sets, scale and ray-drop augmentation); checkpoints with
//! resume like the GAN run.
//!
//! With validation recordings the run scores them every `validate_every_steps` on whole
//! revolutions, keeps the best network by validation mean IoU and stops once that has not
//! improved for `patience` validations: trained until it flattens, chosen on validation.
//!
//! Run directory: `config.json` (written first), `checkpoint/` (network, optimiser,
//! state.json; replaced atomically), `log.jsonl` (training loss; validation IoU per class),
//! and `model/` (the exported model folder: the best on validation, else the last).

use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use burn::config::Config;
use burn::module::Module;
use burn::optim::{AdamConfig, GradientsParams, ModuleOptimizer};
use burn::tensor::Device;
use burn::tensor::activation::softmax;
use serde::{Deserialize, Serialize};

use super::classes::{CLASSES, NUM_CLASSES, SCORED};
use super::data::{CHANNELS, ClassColumns, CropPlan, SegDataset, batch, benchmark_profile};
use super::eval::{confusion, mean_iou};
use super::loss::{
    lovasz_softmax, lovasz_terms, partial_cross_entropy, partial_mask, weighted_cross_entropy,
    weighted_one_hot,
};
use super::net::{SegNet, SegNetConfig};
use super::{SegModel, SegModelInfo};
use crate::train::{CHECKPOINT, open_log, read_state, write_checkpoint};
use crate::util::rng::Rng;
use crate::util::tensor::{tensor_from, tensor_to_vec};

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
    /// Share of crops centred on a drawn class ([`CropPlan::balanced`]).
    #[config(default = 0.5)]
    pub balanced_crops: f32,
    /// Weight of the Lovász-softmax term beside the cross-entropy (0: cross-entropy only).
    #[config(default = 1.0)]
    pub lovasz_weight: f64,
    /// Scale and ray-drop augmentation ([`CropPlan::augment`]).
    #[config(default = false)]
    pub augment: bool,
    /// Steps between validations (when the run has validation recordings).
    #[config(default = 200)]
    pub validate_every_steps: u64,
    /// Validations without a new best mean IoU before the run stops (0: never stops early).
    #[config(default = 6)]
    pub patience: u64,
}

/// How to run (not saved).
#[derive(Debug, Clone)]
pub struct SegTrainOptions {
    pub run_dir: PathBuf,
    pub recordings: Vec<PathBuf>,
    /// Held-out recordings the run is validated and chosen on (none: the last step wins).
    pub validation: Vec<PathBuf>,
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
    #[serde(default)]
    best: Option<Validation>,
    /// Validations since the best.
    #[serde(default)]
    stale: u64,
}

/// One validation's result.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Validation {
    pub step: u64,
    /// Mean IoU over the scored classes present in the validation scans.
    pub miou: f64,
    /// IoU per class (`None`: undefined).
    pub iou: Vec<Option<f64>>,
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
    /// The validation the exported model was chosen by.
    pub best: Option<Validation>,
    /// Stopped because validation stopped improving.
    pub flattened: bool,
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
    let validation = if opts.validation.is_empty() {
        None
    } else {
        Some(SegDataset::from_recordings(
            &opts.validation,
            opts.topic.as_deref(),
            &profile,
        )?)
    };
    let info = SegModelInfo {
        net: config.net.clone(),
        classes: CLASSES.iter().map(|s| s.to_string()).collect(),
        profile,
        trained_on: file_names(&opts.recordings),
        steps: 0,
        seed: config.seed,
    };
    let mut trainer = Trainer::new(&config, &opts.run_dir, &data)?;
    let started = Instant::now();
    let model_dir = opts.run_dir.join("model");
    let flattened = trainer.train(opts, &data, validation.as_ref(), &info, started)?;
    if validation.is_none() {
        let info = SegModelInfo {
            steps: trainer.state.step,
            ..info
        };
        SegModel::save(&info, &trainer.net.valid(), &model_dir)?;
    }
    Ok(SegTrainSummary {
        steps: trainer.state.step,
        total_steps: config.total_steps,
        finished: flattened || trainer.state.step >= config.total_steps,
        scans: data.len(),
        seconds: started.elapsed().as_secs_f64(),
        model_dir,
        best: trainer.state.best.clone(),
        flattened,
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
    plan: CropPlan,
    columns: ClassColumns,
}

impl Trainer {
    fn new(config: &SegTrainConfig, run_dir: &Path, data: &SegDataset) -> Result<Self> {
        crate::model::tune_allocator();
        let device = Device::flex().autodiff();
        let mut rng = Rng::new(config.seed);
        let mut net = config.net.init(&mut rng, &device);
        let mut opt = AdamConfig::new().init();
        let mut state = SegTrainState {
            step: 0,
            rng,
            best: None,
            stale: 0,
        };
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
            state = read_state(&ck)?;
        }
        Ok(Trainer {
            config: config.clone(),
            device,
            net,
            opt,
            state,
            weights: data.class_weights(),
            plan: CropPlan {
                size: config.batch_size,
                crop_width: config.crop_width,
                balanced: config.balanced_crops,
                augment: config.augment,
            },
            columns: ClassColumns::new(data),
        })
    }

    fn lr(&self) -> f64 {
        let t = self.state.step as f64 / self.config.total_steps.max(1) as f64;
        self.config.lr * 0.5 * (1.0 + (std::f64::consts::PI * t.min(1.0)).cos())
    }

    /// Trains until the step budget, the time limit, or (with validation) until validation
    /// flattens; returns whether it flattened.
    fn train(
        &mut self,
        opts: &SegTrainOptions,
        data: &SegDataset,
        validation: Option<&SegDataset>,
        info: &SegModelInfo,
        started: Instant,
    ) -> Result<bool> {
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
        let mut log = open_log(&opts.run_dir, self.state.step)?;
        let mut last_ckpt = Instant::now();
        let mut window = (Instant::now(), self.state.step, 0.0f64);
        let mut flattened = self.flattened();
        while self.state.step < total && !flattened {
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
            if let Some(val) = validation {
                let due = self
                    .state
                    .step
                    .is_multiple_of(self.config.validate_every_steps.max(1))
                    || self.state.step == total;
                if due {
                    self.validate(val, info, &opts.run_dir, &mut log)?;
                    flattened = self.flattened();
                }
            }
            if last_ckpt.elapsed() >= Duration::from_secs(self.config.checkpoint_every_secs) {
                self.checkpoint(&opts.run_dir)?;
                last_ckpt = Instant::now();
            }
            if opts.max_duration.is_some_and(|t| started.elapsed() >= t) {
                break;
            }
        }
        // A run stopped before its first validation still leaves a model to use.
        if let (Some(val), None) = (validation, &self.state.best) {
            self.validate(val, info, &opts.run_dir, &mut log)?;
        }
        self.checkpoint(&opts.run_dir)?;
        bar.finish_and_clear();
        Ok(flattened)
    }

    fn flattened(&self) -> bool {
        self.config.patience > 0 && self.state.stale >= self.config.patience
    }

    /// Scores the network on whole validation revolutions and logs the scores; a new best
    /// is exported to `model/`.
    fn validate(
        &mut self,
        val: &SegDataset,
        info: &SegModelInfo,
        run_dir: &Path,
        log: &mut impl Write,
    ) -> Result<()> {
        let net = self.net.valid();
        let scores = confusion(&net, val, &Device::flex()).scores();
        let v = Validation {
            step: self.state.step,
            miou: mean_iou(&scores, SCORED).unwrap_or(0.0),
            iou: scores.iter().map(|c| c.iou).collect(),
        };
        if self.state.best.as_ref().is_none_or(|b| v.miou > b.miou) {
            let info = SegModelInfo {
                steps: self.state.step,
                ..info.clone()
            };
            SegModel::save(&info, &net, &run_dir.join("model"))?;
            self.state.best = Some(v.clone());
            self.state.stale = 0;
        } else {
            self.state.stale += 1;
        }
        writeln!(log, "{}", serde_json::json!({ "validation": v }))?;
        Ok(())
    }

    /// One Adam step; returns the loss.
    fn step(&mut self, data: &SegDataset) -> f32 {
        let (b, cw, h) = (self.config.batch_size, self.config.crop_width, data.height);
        let (input, target) = batch(data, &self.plan, &self.columns, &mut self.state.rng);
        let shape = [b, NUM_CLASSES, h, cw];
        let x = tensor_from(input, [b, CHANNELS, h, cw], &self.device);
        let (weights, norm) = weighted_one_hot(&target, h * cw, &self.weights);
        let (partial, partial_count) = partial_mask(&target);
        // A partial label weighs as an average labelled return (the class weights' mean).
        let norm = norm + partial_count;
        let weights = tensor_from(weights, shape, &self.device);
        let logits = self.net.forward(x, false);
        let mut loss = weighted_cross_entropy(logits.clone(), weights, norm);
        if partial_count > 0.0 {
            let mask = tensor_from(partial, [b, 1, h, cw], &self.device);
            loss = loss + partial_cross_entropy(logits.clone(), mask).div_scalar(norm);
        }
        if self.config.lovasz_weight > 0.0 {
            let probs = softmax(logits, 1);
            let terms = lovasz_terms(&tensor_to_vec(probs.clone()), &target, h * cw);
            let lovasz = lovasz_softmax(
                probs,
                tensor_from(terms.one_hot, shape, &self.device),
                tensor_from(terms.weights, shape, &self.device),
            );
            loss = loss + lovasz.mul_scalar(self.config.lovasz_weight);
        }
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
