//! Reconstruction-assisted GAN training: an encoder in the generator's loop, so that every real
//! scan teaches the generator directly (as in ALAE, VAE-GAN and BigBiGAN), not only through
//! the discriminator's judgement of random samples.
//!
//! Each generator step also encodes a batch of real scans, w_hat = w_avg + E(scan), renders
//! w_hat and scores the rendering against the scan: L1 on inverse depth where the scan has a
//! return, and the keep logit against the scan's return mask (the ray-drop model is trained on
//! what the sensor actually dropped). A latent cycle keeps the encoder's outputs where the
//! mapping network puts random latents: E of a measured fake must give back its w. A prior
//! match keeps the encoded real scans spread as the mapped latents are: without it the
//! encoder can put every scan at one point, and the reconstruction then teaches the generator
//! the mean scan there. The generator takes the adversarial and the reconstruction gradients;
//! the encoder takes the reconstruction, the cycle and the prior match. `convert` inverts real
//! scans the same way, so this trains for what the tool does with the generator.

use burn::config::Config;
use burn::optim::{AdamConfig, ModuleOptimizer};
use burn::tensor::activation::softplus;
use burn::tensor::{Device, Tensor};

use super::growth::Level;
use crate::decode::amortised::{Encoder, EncoderConfig};
use crate::model::data::DROPPED;
use crate::model::generator::{Generator, GridCache};

/// The weights of reconstruction-assisted training (part of the run's config).
#[derive(Config, Debug, PartialEq)]
pub struct ReconstructionConfig {
    /// Weight of the reconstruction loss in the generator's step.
    #[config(default = 1.0)]
    pub weight: f32,
    /// Weight of the keep-logit (ray-drop) term inside the reconstruction loss.
    #[config(default = 0.1)]
    pub keep_weight: f32,
    /// Weight of the encoder's latent cycle ||E(G(w)) - (w - w_avg)||^2 / d_w.
    #[config(default = 1.0)]
    pub cycle_weight: f32,
    /// Weight of the prior match: the squared gaps between the per-dimension means and
    /// standard deviations of the encoded real scans and of the mapped latents.
    #[config(default = 0.0)]
    pub prior_weight: f32,
    /// Adam learning rate of the encoder.
    #[config(default = 1e-3)]
    pub lr: f64,
    #[config(default = 11)]
    pub seed: u64,
}

/// The encoder of the current level and its optimiser.
pub struct InLoopEncoder {
    pub encoder: Encoder,
    pub opt: ModuleOptimizer,
}

impl InLoopEncoder {
    /// A fresh encoder for `level`'s grid, producing latents of size `d_w`.
    pub fn new(config: &ReconstructionConfig, level: &Level, d_w: usize, device: &Device) -> Self {
        let encoder = EncoderConfig::new()
            .with_height(level.height)
            .with_width(level.width)
            .with_d_w(d_w)
            .with_seed(config.seed)
            .init(device);
        Self {
            encoder,
            opt: AdamConfig::new().with_epsilon(1e-8).init(),
        }
    }
}

/// The losses of one part of a batch, as scalars for the log.
#[derive(Debug, Clone, Copy, Default)]
pub struct Losses {
    pub reconstruction: f32,
    pub cycle: f32,
    pub prior: f32,
}

/// Mean absolute difference of inverse depth over the scan's returns.
///
/// # Shapes
/// - x_d, real, returns: `[n, 1, H, W]` (network units; returns in {0, 1})
pub fn returns_l1(x_d: Tensor<4>, real: Tensor<4>, returns: Tensor<4>) -> Tensor<1> {
    let count = returns.clone().sum().add_scalar(1.0);
    ((x_d - real).abs() * returns).sum() / count
}

/// How far a batch of encoded latents lies from the mapped latents' distribution: the squared
/// gaps between their per-dimension means and standard deviations, averaged over dimensions.
/// A batch encoded into one tight cloud scores the mapped latents' variance however well
/// its mean sits.
///
/// # Shapes
/// - encoded, mapped: `[n, d_w]` (both relative to w_avg)
pub fn moment_gap(encoded: Tensor<2>, mapped: Tensor<2>) -> Tensor<1> {
    let moments = |x: Tensor<2>| {
        let mean = x.clone().mean_dim(0); // [1, d_w]
        let var = (x - mean.clone()).powi_scalar(2).mean_dim(0);
        (mean, var.add_scalar(1e-8).sqrt())
    };
    let (mean_e, std_e) = moments(encoded);
    let (mean_m, std_m) = moments(mapped);
    ((mean_e - mean_m).powi_scalar(2) + (std_e - std_m).powi_scalar(2)).mean()
}

/// The reconstruction-assisted terms for one part of a batch, weighted, with their values.
///
/// # Shapes
/// - real: `[n, 1, H, W]` network units (no return = -1), on the level's grid
/// - fake: `[n, 1, H, W]` measured fakes (no gradient reaches the generator through them)
/// - w: `[n, d_w]` the fakes' latents (targets only)
pub fn losses(
    config: &ReconstructionConfig,
    generator: &Generator,
    encoder: &Encoder,
    grid: &GridCache,
    real: Tensor<4>,
    fake: Tensor<4>,
    w: Tensor<2>,
) -> (Tensor<1>, Losses) {
    let w_avg = generator.mapping.w_avg.val().detach().unsqueeze::<2>(); // [1, d_w]
    let returns = real.clone().greater_elem(DROPPED).float(); // [n, 1, H, W]
    let encoded = encoder.forward(real.clone(), returns.clone()); // [n, d_w], relative to w_avg
    let w_hat = encoded.clone() + w_avg.clone();
    let out = generator.render(w_hat, grid, None);
    let depth = returns_l1(out.x_d, real, returns.clone()); // [1]
    let logit = out.keep_logit; // [n, 1, H, W]
    let keep = (softplus(logit.clone().neg(), 1.0) * returns.clone()
        + softplus(logit, 1.0) * returns.neg().add_scalar(1.0))
    .mean(); // [1]
    let reconstruction = depth + keep.mul_scalar(config.keep_weight);
    let fake = fake.detach();
    let fake_returns = fake.clone().greater_elem(DROPPED).float();
    let [n, d_w] = w.dims();
    let target = w.detach() - w_avg; // [n, d_w]
    let prior = moment_gap(encoded, target.clone());
    let cycle = (encoder.forward(fake, fake_returns) - target)
        .powi_scalar(2)
        .sum()
        .div_scalar((n * d_w).max(1) as f32); // [1]
    let values = Losses {
        reconstruction: reconstruction.clone().inner().into_scalar::<f32>(),
        cycle: cycle.clone().inner().into_scalar::<f32>(),
        prior: prior.clone().inner().into_scalar::<f32>(),
    };
    let total = reconstruction.mul_scalar(config.weight)
        + cycle.mul_scalar(config.cycle_weight)
        + prior.mul_scalar(config.prior_weight);
    (total, values)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::generator::GeneratorConfig;
    use crate::model::layers::kitti_like_grid;
    use crate::util::rng::Rng;
    use burn::optim::GradientsParams;

    /// The gap is near zero for two samples of one distribution, large for a collapsed
    /// batch, and its gradient spreads a collapsed batch out.
    #[test]
    fn moment_gap_sees_and_undoes_a_collapsed_batch() {
        let device = Device::flex().autodiff();
        let mut rng = Rng::new(7);
        let mapped = rng.normal_tensor([256, 8], &device);
        let other = rng.normal_tensor([256, 8], &device);
        let same = moment_gap(other, mapped.clone()).into_scalar::<f32>();
        assert!(same < 0.05, "two samples of N(0, I): {same}");
        let collapsed = rng
            .normal_tensor([256, 8], &device)
            .mul_scalar(0.05)
            .add_scalar(1.0);
        let gap = moment_gap(collapsed.clone(), mapped.clone()).into_scalar::<f32>();
        assert!(gap > 1.5, "a tight cloud off the mean: {gap}");
        let mut x = collapsed;
        for _ in 0..50 {
            let leaf = x.detach().require_grad();
            let grads = moment_gap(leaf.clone(), mapped.clone()).backward();
            let step = leaf.grad(&grads).expect("x takes a gradient");
            x = leaf.detach() - step.mul_scalar(50.0);
        }
        let after = moment_gap(x, mapped).into_scalar::<f32>();
        assert!(after < 0.1 * gap, "{gap} -> {after}");
    }

    /// A few steps on the reconstruction loss alone bring the rendering of an encoded scan
    /// closer to the scan: the gradients reach both the generator and the encoder.
    #[test]
    fn reconstruction_steps_lower_the_reconstruction_loss() {
        let inner = Device::flex();
        let device = inner.clone().autodiff();
        let g_config = GeneratorConfig::cpu()
            .with_channels(vec![16, 8, 8])
            .with_n_freq(vec![4, 4, 4])
            .with_lh(vec![3, 4, 5])
            .with_lw(vec![3, 4, 5]);
        let mut g = g_config.init(&device);
        let level = Level {
            blocks: 3,
            factor: 1,
            height: 16,
            width: 64,
            window: None,
        };
        let config = ReconstructionConfig::new().with_cycle_weight(0.0);
        let mut e = InLoopEncoder::new(&config, &level, g.d_w(), &device);
        let mut opt_g = AdamConfig::new().init();
        let grid = g.prepare(&kitti_like_grid(16, 64), &device);
        let mut rng = Rng::new(5);
        // A "scan": a ramp of inverse depth with a band of drops.
        let real: Vec<f32> = (0..2 * 16 * 64)
            .map(|k| {
                let r = (k / 64) % 16;
                if r < 2 {
                    -1.0
                } else {
                    -0.9 + 1.5 * r as f32 / 16.0
                }
            })
            .collect();
        let real = crate::util::tensor::tensor_from(real, [2, 1, 16, 64], &device);
        let z = rng.normal_tensor([2, g.d_z()], &device);
        let mut first = None;
        let mut last = 0.0;
        for _ in 0..30 {
            let w = g.mapping.forward(z.clone());
            let fake = g.render(w.clone(), &grid, None).x_d;
            let (loss, values) = losses(&config, &g, &e.encoder, &grid, real.clone(), fake, w);
            let mut grads = loss.backward();
            let g_grads = GradientsParams::from_module(&mut grads, &g);
            let e_grads = GradientsParams::from_module(&mut grads, &e.encoder);
            g = opt_g.step(1e-2, g, g_grads);
            e.encoder = e.opt.step(1e-2, e.encoder.clone(), e_grads);
            first.get_or_insert(values.reconstruction);
            last = values.reconstruction;
        }
        let first = first.expect("steps ran");
        assert!(last < 0.6 * first, "{first} -> {last}");
    }
}
