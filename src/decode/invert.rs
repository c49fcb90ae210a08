//! Optimisation-based inversion (reference section 5): Adam on the latent w with a cosine
//! learning-rate ramp, then pivotal tuning (PTI): w frozen, every generator weight fine-tuned.
//! Both qualities refine the encoder's prediction: `--quality paper` with 500 tuning steps,
//! `--quality fast` with 33. The paper's own schedule (500 + 500 steps from w_avg) is
//! [`Schedule::reference`].

use burn::module::Module;
use burn::optim::{AdamConfig, GradientsParams};
use burn::tensor::{Device, Tensor};

use super::loss::{pool_masked, reconstruction_loss};
use crate::model::generator::{Generator, GridCache};
use crate::util::adam::Adam;
use crate::util::tensor::{tensor_from, tensor_to_vec};

/// Steps and learning rates of one inversion.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Schedule {
    /// Adam steps on w.
    pub w_steps: usize,
    /// Peak learning rate on w.
    pub w_lr: f64,
    /// Pivotal-tuning steps on the generator weights (w frozen).
    pub tune_steps: usize,
    /// Learning rate of pivotal tuning (constant, or the peak with `tune_decay`).
    pub tune_lr: f64,
    /// Cosine decay of the tuning learning rate from `tune_lr` to 0.
    #[serde(default)]
    pub tune_decay: bool,
    /// Learning rate of w while tuning (0 = w frozen, the paper's pivotal tuning).
    #[serde(default)]
    pub tune_w_lr: f64,
    /// Masked 2x2-pooled pyramid levels added to the loss.
    pub pyramid_levels: usize,
    /// Tuning steps before `tune_steps`, coarsest first: the last entry renders with all but
    /// the generator's finest block, at half the model grid's resolution, each earlier one with
    /// one block fewer at half the next's, against the observation pooled to it
    /// ([`pool_masked`]). A coarse step costs a fraction of a full-resolution one (most of the
    /// generator's work is in its finest blocks).
    #[serde(default)]
    pub coarse_steps: Vec<usize>,
    /// Pivotal tuning leaves every layer's bias and the blocks' output heads as trained, and
    /// moves only the synthesis layers' weights and style maps. In the same steps it fits a scan
    /// better than moving every weight (the paper's): a few steps cannot move a head or a bias
    /// without shifting the whole scene (BENCHMARKS.md, "Pivotal tuning of weights and styles
    /// only").
    #[serde(default)]
    pub keep_heads_and_biases: bool,
}

impl Schedule {
    /// `--quality paper`: 500 steps of pivotal tuning after the encoder, the learning rate
    /// decayed from 4e-2 to 0 along a cosine. Chosen on a KITTI drive left out of training:
    /// 0.042 relative L1 there against 0.061 for the paper's own schedule
    /// ([`Schedule::reference`]), in half its time; 2e-2 and 8e-2 did worse, and so did a
    /// constant rate.
    pub fn paper() -> Self {
        Schedule {
            w_steps: 0,
            w_lr: 0.02,
            tune_steps: 500,
            tune_lr: 4e-2,
            tune_decay: true,
            tune_w_lr: 0.0,
            pyramid_levels: 2,
            coarse_steps: Vec::new(),
            keep_heads_and_biases: true,
        }
    }

    /// The paper's schedule, from w_avg: 500 steps on w (lr 0.05, cosine ramp-down), 500 of
    /// pivotal tuning (lr 5e-4). Kept to compare against.
    pub fn reference() -> Self {
        Schedule {
            w_steps: 500,
            w_lr: 0.05,
            tune_steps: 500,
            tune_lr: 5e-4,
            tune_decay: false,
            tune_w_lr: 0.0,
            pyramid_levels: 2,
            coarse_steps: Vec::new(),
            keep_heads_and_biases: false,
        }
    }

    /// The fast path's refinement after the encoder: 33 steps of pivotal tuning of the synthesis
    /// weights and styles at 40x the paper's tuning rate, no steps on w. 33 steps run `convert`
    /// at 9.4 scans/s end to end on 2 quiet AVX-512 cores (a step costs ~6 ms per scan and core by
    /// hand; BENCHMARKS.md); the learning rate was chosen on a KITTI drive left out of training
    /// (2e-2 among 1e-2..2.8e-2 with heads and biases kept; a cosine decay was worse). Steps on w
    /// after the encoder made the result worse.
    ///
    /// [`Schedule::with_coarse_steps`] trades it for a faster coarse-to-fine schedule: better on
    /// that drive, worse on the held-out scans (BENCHMARKS.md), so not the default.
    pub fn fast() -> Self {
        Schedule {
            w_steps: 0,
            w_lr: 0.02,
            tune_steps: 33,
            tune_lr: 2e-2,
            tune_decay: false,
            tune_w_lr: 0.0,
            pyramid_levels: 2,
            coarse_steps: Vec::new(),
            keep_heads_and_biases: true,
        }
    }

    /// Coarse-to-fine tuning: `coarse` steps (coarsest first, e.g. `[48, 48, 4]` at 8 x 64,
    /// 16 x 128 and 32 x 256 on the model grid) before `fine` full-resolution steps whose rate
    /// decays to 0 ([`Schedule::fine_decay`]). An empty `coarse` leaves `fine` constant-rate
    /// steps.
    pub fn with_coarse_steps(mut self, coarse: &[usize], fine: usize) -> Self {
        self.tune_steps = fine;
        self.coarse_steps = coarse.to_vec();
        self
    }

    /// Whether the full-resolution steps decay their rate linearly to 0: they do after coarse
    /// steps, since a few steps after coarse ones end mid-oscillation at a constant rate.
    pub fn fine_decay(&self) -> bool {
        !self.coarse_steps.is_empty()
    }

    /// `n` pivotal-tuning steps, all at full resolution at a constant (or cosine) rate: an
    /// explicit step count replaces the coarse-to-fine schedule.
    pub fn set_tune_steps(&mut self, n: usize) {
        self.tune_steps = n;
        self.coarse_steps.clear();
    }

    /// The step counts in words, e.g. `0 w + 5 tuning (after 48/48/4 coarse)`.
    pub fn describe(&self) -> String {
        let text = format!("{} w + {} tuning", self.w_steps, self.tune_steps);
        if self.coarse_steps.is_empty() {
            return text;
        }
        let coarse: Vec<String> = self.coarse_steps.iter().map(usize::to_string).collect();
        format!("{text} (after {} coarse)", coarse.join("/"))
    }

    /// The tuning rate at tuning step `step` of `total`: constant, or along the cosine decay.
    pub fn tuning_rate(&self, step: usize, total: usize) -> f64 {
        if !self.tune_decay {
            return self.tune_lr;
        }
        let t = step as f64 / total as f64;
        self.tune_lr * 0.5 * (1.0 + (std::f64::consts::PI * t).cos())
    }

    /// Total optimisation steps (each one forward + backward pass of the generator).
    pub fn steps(&self) -> usize {
        self.w_steps + self.coarse_steps.iter().sum::<usize>() + self.tune_steps
    }
}

/// The StyleGAN2 projector's ramp: linear ramp-up over the first 5 %, cosine ramp-down over the
/// last 25 % of `t` in [0, 1].
pub fn lr_ramp(t: f64) -> f64 {
    let down = ((1.0 - t) / 0.25).min(1.0);
    let down = 0.5 - 0.5 * (down * std::f64::consts::PI).cos();
    down * (t / 0.05).min(1.0)
}

/// A tuned generator and its pivot latent, on the inference device.
#[derive(Debug, Clone)]
pub struct Inverted {
    pub generator: Generator,
    /// `[1, d_w]`
    pub w: Vec<f32>,
    /// Loss after each step (w steps, then tuning steps).
    pub losses: Vec<f32>,
}

/// What one tuning step is fitted to: a grid and the observation on it.
struct Fit {
    cache: GridCache,
    target: Tensor<4>,
    mask: Tensor<4>,
}

/// The tuning steps of `schedule` and what each group is fitted to, coarsest first.
fn fits(
    cache: &GridCache,
    target: Tensor<4>,
    mask: Tensor<4>,
    schedule: &Schedule,
) -> Vec<(usize, Fit)> {
    let blocks = cache.levels.len();
    let mut stages = vec![(
        schedule.tune_steps,
        Fit {
            cache: cache.clone(),
            target,
            mask,
        },
    )];
    for (k, steps) in schedule.coarse_steps.iter().rev().enumerate() {
        if k + 1 >= blocks {
            break; // nothing coarser than the first block
        }
        let finer = &stages.last().expect("the full-resolution fit").1;
        let (target, mask) = pool_masked(finer.target.clone(), finer.mask.clone());
        let fit = Fit {
            cache: cache.first_blocks(blocks - k - 1),
            target,
            mask,
        };
        stages.push((*steps, fit));
    }
    stages.reverse();
    stages
}

/// Invert one observation through burn's autodiff, whatever the schedule.
///
/// `generator` lives on the inference device, `cache_ad` is its grid cache on `ad` (the
/// autodiff device); target and mask are `[1, 1, H, W]` on `ad` (network units, {0, 1}).
/// Starts at `w0`. The caller's generator is not modified: pivotal tuning works on a copy.
/// [`super::pivotal::Tuning`] runs schedules of pivotal tuning alone faster, by hand.
pub fn invert(
    generator: &Generator,
    cache_ad: &GridCache,
    target: Tensor<4>,
    mask: Tensor<4>,
    w0: Vec<f32>,
    schedule: &Schedule,
    ad: &Device,
) -> Inverted {
    let d_w = w0.len();
    let mut w = w0;
    let mut losses = Vec::with_capacity(schedule.steps());
    let levels = schedule.pyramid_levels;

    // Step 1: w only; the weights are constants (no weight gradients are computed).
    if schedule.w_steps > 0 {
        let frozen = generator.clone().fork(ad).no_grad();
        let mut adam = Adam::new(d_w);
        for step in 0..schedule.w_steps {
            let t = step as f64 / schedule.w_steps as f64;
            let lr = (schedule.w_lr * lr_ramp(t)) as f32;
            let w_t = tensor_from(w.clone(), [1, d_w], ad).require_grad(); // [1, d_w]
            let x_d = frozen.render(w_t.clone(), cache_ad, None).x_d; // [1, 1, H, W]
            let loss = reconstruction_loss(x_d, target.clone(), mask.clone(), levels).sum();
            losses.push(loss.clone().inner().into_scalar::<f32>());
            let grads = loss.backward();
            let Some(g) = w_t.grad(&grads) else { break };
            let g = tensor_to_vec(g);
            adam.step(&mut w, &g, lr);
        }
    }

    // Step 2: pivotal tuning of every weight with w frozen; the coarse steps first.
    let stages = fits(cache_ad, target, mask, schedule);
    let total: usize = stages.iter().map(|(steps, _)| steps).sum();
    let mut tuned = generator.clone().fork(ad).train();
    let joint = schedule.tune_w_lr > 0.0;
    let mut adam_w = Adam::new(d_w);
    let mut opt = AdamConfig::new().with_epsilon(1e-8).init();
    let mut step = 0;
    for (steps, fit) in &stages {
        let full_resolution = fit.cache.height == cache_ad.height;
        for i in 0..*steps {
            let lr = if !schedule.tune_decay && schedule.fine_decay() && full_resolution {
                schedule.tune_lr * (1.0 - i as f64 / *steps as f64)
            } else {
                schedule.tuning_rate(step, total)
            };
            step += 1;
            let w_t = tensor_from(w.clone(), [1, d_w], ad); // [1, d_w]
            let w_t = if joint { w_t.require_grad() } else { w_t };
            let x_d = tuned.render(w_t.clone(), &fit.cache, None).x_d; // [1, 1, h, w]
            let loss = reconstruction_loss(x_d, fit.target.clone(), fit.mask.clone(), levels).sum();
            losses.push(loss.clone().inner().into_scalar::<f32>());
            let mut grads = loss.backward();
            if joint && let Some(g) = w_t.grad_remove(&mut grads) {
                adam_w.step(&mut w, &tensor_to_vec(g), schedule.tune_w_lr as f32);
            }
            let mut grads = GradientsParams::from_grads(grads, &tuned);
            if schedule.keep_heads_and_biases {
                keep_heads_and_biases(&tuned, &mut grads);
            }
            tuned = opt.step(lr, tuned, grads);
        }
    }
    Inverted {
        generator: tuned.valid(),
        w,
        losses,
    }
}

/// Drops the gradients of every bias and of the output heads, so that the optimiser leaves
/// them as they are ([`Schedule::keep_heads_and_biases`]).
fn keep_heads_and_biases(generator: &Generator, grads: &mut GradientsParams) {
    for block in &generator.blocks {
        for layer in [&block.conv0, &block.conv1] {
            grads.remove::<1>(layer.bias.id);
        }
        let head = &block.head;
        grads.remove::<2>(head.weight.id);
        grads.remove::<2>(head.affine.weight.id);
        grads.remove::<1>(head.affine.bias.id);
        grads.remove::<1>(head.bias.id);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::generator::{GeneratorConfig, MappingConfig};
    use crate::model::layers::kitti_like_grid;
    use crate::util::rng::Rng;

    #[test]
    fn ramp_rises_then_falls_to_zero() {
        assert_eq!(lr_ramp(0.0), 0.0);
        assert!((lr_ramp(0.5) - 1.0).abs() < 1e-12);
        assert!(lr_ramp(0.9) < 1.0 && lr_ramp(0.9) > 0.0);
        assert!(lr_ramp(1.0).abs() < 1e-12);
    }

    /// A two-block generator, its grid caches (inference, autodiff) and a reachable target.
    fn toy() -> (Generator, GridCache, GridCache, Tensor<4>) {
        let dev = Device::flex();
        let ad = dev.clone().autodiff();
        let g = GeneratorConfig::new()
            .with_mapping(MappingConfig::new().with_d_z(8).with_d_w(8))
            .with_channels(vec![8, 8])
            .with_n_freq(vec![4, 4])
            .with_lh(vec![3, 4])
            .with_lw(vec![2, 3])
            .with_seed(3)
            .init(&dev);
        let grid = kitti_like_grid(8, 32);
        let cache = g.prepare(&grid, &dev);
        let cache_ad = g.prepare(&grid, &ad);
        // The target: another latent's image.
        let mut rng = Rng::new(4);
        let w_true = g.mapping.forward(rng.normal_tensor([1, 8], &dev));
        let target = g.render(w_true, &cache, None).x_d;
        (g, cache, cache_ad, target)
    }

    #[test]
    fn both_stages_lower_the_loss_and_leave_the_input_generator_alone() {
        let (g, cache, cache_ad, target) = toy();
        let (dev, ad) = (Device::flex(), Device::flex().autodiff());
        let before = tensor_to_vec(g.render(Tensor::zeros([1, 8], &dev), &cache, None).x_d);
        let mask = target.ones_like();
        let sched = Schedule {
            w_steps: 30,
            w_lr: 0.1,
            tune_steps: 30,
            tune_lr: 3e-3,
            tune_decay: false,
            tune_w_lr: 0.0,
            pyramid_levels: 1,
            coarse_steps: Vec::new(),
            keep_heads_and_biases: false,
        };
        let inv = invert(
            &g,
            &cache_ad,
            target.clone().autodiff(),
            mask.autodiff(),
            vec![0.0; 8],
            &sched,
            &ad,
        );
        let l = &inv.losses;
        assert_eq!(l.len(), 60);
        assert!(l[29] < l[0], "w stage: {} -> {}", l[0], l[29]);
        assert!(l[59] < l[30], "tuning stage: {} -> {}", l[30], l[59]);
        let after = tensor_to_vec(g.render(Tensor::zeros([1, 8], &dev), &cache, None).x_d);
        assert_eq!(before, after, "the shared generator must not be tuned");
    }

    #[test]
    fn coarse_steps_fit_the_pooled_observation_and_help_the_full_grid() {
        let (g, _, cache_ad, target) = toy();
        let ad = Device::flex().autodiff();
        let mask = target.ones_like().autodiff();
        let base = Schedule {
            tune_lr: 3e-3,
            pyramid_levels: 1,
            ..Schedule::fast()
        };
        let run = |sched: &Schedule| {
            let inv = invert(
                &g,
                &cache_ad,
                target.clone().autodiff(),
                mask.clone(),
                vec![0.0; 8],
                sched,
                &ad,
            );
            inv.losses
        };
        let plain = run(&base.clone().with_coarse_steps(&[], 4));
        let c2f = run(&base.clone().with_coarse_steps(&[40], 4));
        assert_eq!(c2f.len(), 44);
        // The coarse steps see the 4 x 16 half grid (first block only) and fit it.
        assert!(
            c2f[39] < 0.5 * c2f[0],
            "coarse stage: {} -> {}",
            c2f[0],
            c2f[39]
        );
        // Starting from them, the full grid is fitted better than by its own 4 steps.
        assert!(
            c2f[43] < plain[3],
            "coarse to fine {} vs plain {}",
            c2f[43],
            plain[3]
        );
    }

    #[test]
    fn schedules_say_what_they_run() {
        let fast = Schedule::fast();
        assert_eq!(fast.describe(), "0 w + 33 tuning");
        let c2f = fast.clone().with_coarse_steps(&[48, 48, 4], 5);
        assert_eq!(c2f.describe(), "0 w + 5 tuning (after 48/48/4 coarse)");
        assert_eq!(c2f.steps(), 105);
        assert!(c2f.fine_decay());
        let mut back = c2f;
        back.set_tune_steps(33);
        assert_eq!(
            back, fast,
            "an explicit step count replaces the coarse schedule"
        );
    }
}
