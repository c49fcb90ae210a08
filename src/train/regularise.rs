//! Discriminator regularisers for small data, each switched on alone or together beside the
//! adaptive augmentation (ADA) of [`super::update`], so that each can be measured against
//! ADA alone. With some 600 real scans a discriminator learns them by heart: it scores the
//! scans it trained on far above real scans it never saw, and stops teaching the generator.
//!
//! - **LeCam** (Tseng et al. 2021): D's logits on reals are pulled toward the moving average
//!   of its logits on fakes and the other way round, wherever they overshoot it; this bounds
//!   how far apart D can push the two sets.
//! - **DiffAugment-style translation and cutout** (Zhao et al. 2020), on every image D sees,
//!   real and fake, in D's step and G's: a vertical shift by up to 1/8 of the beams (the rows
//!   shifted in are dropped rays), a circular shift by up to 1/8 of a revolution, and one
//!   rectangle of half the height and width dropped. Built as products with host matrices so
//!   gradients reach the generator.
//! - **APA** (Jiang et al. 2021): with an adaptive probability each real image in D's batch
//!   is replaced by a generated one, still labelled real; the probability follows the same
//!   overfitting heuristic as ADA (E[sign(D(real))] against its target), on the reals left.
//! - **A self-supervised discriminator** (FastGAN, Liu et al. 2021): a small decoder rebuilds
//!   each real scan from D's last features, and D learns from that loss as well
//!   ([`crate::model::self_decoder`]).

use burn::config::Config;
use burn::tensor::Tensor;
use burn::tensor::activation::relu;

use crate::util::rng::Rng;
use crate::util::tensor::tensor_from;

/// Which regularisers a run's discriminator trains with (all off by default).
#[derive(Config, Debug, PartialEq)]
pub struct DRegularisation {
    /// Weight of the LeCam term; 0: off. Its authors use 0.1-0.3 for small datasets.
    #[config(default = 0.0)]
    pub lecam: f32,
    /// DiffAugment-style translation and cutout of everything D sees.
    #[config(default = false)]
    pub diff_augment: bool,
    /// Adaptive pseudo augmentation: generated images shown to D as real.
    #[config(default = false)]
    pub apa: bool,
    /// Weight of the FastGAN-style self-supervised reconstruction of real scans from D's
    /// last features ([`crate::model::self_decoder`]); 0: off.
    #[config(default = 0.0)]
    pub self_supervised: f32,
}

/// Decay per D step of the moving averages of D's logits the LeCam term anchors to.
pub const LECAM_DECAY: f32 = 0.99;

/// The moving averages of D's mean logit on reals and on fakes.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LecamAnchors {
    pub real: f32,
    pub fake: f32,
}

impl LecamAnchors {
    /// The anchors after a step whose mean logits were `real` and `fake`; the first step's
    /// means start them.
    pub fn update(anchors: Option<Self>, real: f32, fake: f32) -> Self {
        match anchors {
            Some(a) => LecamAnchors {
                real: LECAM_DECAY * a.real + (1.0 - LECAM_DECAY) * real,
                fake: LECAM_DECAY * a.fake + (1.0 - LECAM_DECAY) * fake,
            },
            None => LecamAnchors { real, fake },
        }
    }

    /// The LeCam term (unweighted) of one part's logits `[n, 1]`: the squared overshoot of
    /// real logits above the fakes' average and of fake logits below the reals'.
    pub fn penalty(self, logit_real: Tensor<2>, logit_fake: Tensor<2>) -> Tensor<1> {
        let real = relu(logit_real.sub_scalar(self.fake)).powi_scalar(2).mean();
        let fake = relu(logit_fake.neg().add_scalar(self.real))
            .powi_scalar(2)
            .mean();
        real + fake
    }
}

/// DiffAugment-style translation and cutout of a batch `[batch, 1, H, W]` in network units
/// (-1 = dropped ray): see the module docs.
pub fn translate_cutout(x: Tensor<4>, rng: &mut Rng) -> Tensor<4> {
    let [b, c, h, w] = x.dims();
    debug_assert_eq!(c, 1);
    let device = x.device();
    let mut rows = vec![0f32; b * h * h];
    let mut cols = vec![0f32; b * w * w];
    let mut keep = vec![1f32; b * h * w];
    let (max_dy, max_dx) = ((h / 8) as i64, (w / 8) as i64);
    let (cut_h, cut_w) = (h / 2, w / 2);
    for i in 0..b {
        let dy = rng.below(2 * max_dy as usize + 1) as i64 - max_dy;
        let dx = rng.below(2 * max_dx as usize + 1) as i64 - max_dx;
        // out[r] = x[r - dy] where that row exists; rows shifted in stay 0 (dropped below).
        for r in 0..h as i64 {
            let src = r - dy;
            if (0..h as i64).contains(&src) {
                rows[i * h * h + r as usize * h + src as usize] = 1.0;
            }
        }
        // out[j] = x[(j - dx) mod W]: a revolution has no edge.
        for j in 0..w as i64 {
            let src = (j - dx).rem_euclid(w as i64) as usize;
            cols[i * w * w + src * w + j as usize] = 1.0;
        }
        // One rectangle, its centre anywhere; clipped at the top and bottom rows, wrapped
        // around in azimuth.
        let (cy, cx) = (rng.below(h) as i64, rng.below(w));
        for r in (cy - cut_h as i64 / 2).max(0)..(cy + cut_h as i64 / 2).min(h as i64) {
            for k in 0..cut_w {
                let col = (cx + w - cut_w / 2 + k) % w;
                keep[(i * h + r as usize) * w + col] = 0.0;
            }
        }
    }
    let a = tensor_from(rows, [b, 1, h, h], &device);
    let m = tensor_from(cols, [b, 1, w, w], &device);
    let keep = tensor_from(keep, [b, 1, h, w], &device);
    // In "return + 1" units a dropped ray is 0, so padding and cutout are multiplications.
    let moved = a.matmul(x.add_scalar(1.0)).matmul(m);
    (moved * keep).sub_scalar(1.0)
}

/// APA's batch: each real image replaced by the generated one beside it with probability
/// `p`; returns the mixed batch and which images were replaced.
pub fn pseudo_reals(
    real: Tensor<4>,
    fake: Tensor<4>,
    p: f32,
    rng: &mut Rng,
) -> (Tensor<4>, Vec<bool>) {
    let n = real.dims()[0];
    if p <= 0.0 {
        // No draws: a run without APA keeps the random stream it always had.
        return (real, vec![false; n]);
    }
    let swapped: Vec<bool> = (0..n).map(|_| rng.chance(p)).collect();
    if !swapped.iter().any(|&s| s) {
        return (real, swapped);
    }
    let sel: Vec<f32> = swapped.iter().map(|&s| f32::from(u8::from(s))).collect();
    let sel = tensor_from(sel, [n, 1, 1, 1], &real.device());
    let mixed = real * sel.clone().neg().add_scalar(1.0) + fake.detach() * sel;
    (mixed, swapped)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::util::tensor::tensor_to_vec;
    use burn::tensor::Device;

    #[test]
    fn translate_cutout_moves_returns_and_drops_the_rest() {
        let device = Device::flex();
        let (b, h, w) = (4, 16, 32);
        // Every pixel a distinct return in (-1, 1).
        let v: Vec<f32> = (0..b * h * w)
            .map(|k| (k % (h * w)) as f32 / (h * w) as f32 * 1.8 - 0.9)
            .collect();
        let x = tensor_from(v.clone(), [b, 1, h, w], &device);
        let y = tensor_to_vec(translate_cutout(x, &mut Rng::new(3)));
        for i in 0..b {
            let img = &y[i * h * w..(i + 1) * h * w];
            let dropped = img.iter().filter(|&&p| p <= -1.0 + 1e-6).count();
            // The cutout (a quarter of the image, less where clipped) and rows shifted in.
            assert!(dropped > 0 && dropped <= h * w / 4 + 2 * w, "{dropped}");
            // Every return left is one of the input's values, moved intact.
            for &p in img.iter().filter(|&&p| p > -1.0 + 1e-6) {
                assert!(
                    v[i * h * w..]
                        .iter()
                        .take(h * w)
                        .any(|&q| (q - p).abs() < 1e-5),
                    "{p} is not an input value"
                );
            }
        }
    }

    #[test]
    fn lecam_penalises_only_overshoot() {
        let device = Device::flex();
        let a = LecamAnchors {
            real: 1.0,
            fake: -1.0,
        };
        let t = |v: Vec<f32>| tensor_from(v, [2, 1], &device);
        // Reals below the fakes' average and fakes above the reals' average: no penalty.
        let none = a.penalty(t(vec![-2.0, -1.5]), t(vec![1.5, 2.0]));
        assert_eq!(none.into_scalar::<f32>(), 0.0);
        // Reals 2 above the fakes' average, fakes 3 below the reals': (4 + 9) over their means.
        let some = a.penalty(t(vec![1.0, 1.0]), t(vec![-2.0, -2.0]));
        assert!((some.into_scalar::<f32>() - 13.0).abs() < 1e-5);
        let moved = LecamAnchors::update(Some(a), 2.0, -2.0);
        assert!((moved.real - 1.01).abs() < 1e-6 && (moved.fake + 1.01).abs() < 1e-6);
    }

    #[test]
    fn pseudo_reals_swap_at_their_rate() {
        let device = Device::flex();
        let n = 400;
        let real = tensor_from(vec![0.5; n * 4], [n, 1, 2, 2], &device);
        let fake = tensor_from(vec![-0.5; n * 4], [n, 1, 2, 2], &device);
        let (mixed, swapped) = pseudo_reals(real, fake, 0.25, &mut Rng::new(9));
        let v = tensor_to_vec(mixed);
        let share = swapped.iter().filter(|&&s| s).count() as f32 / n as f32;
        assert!((share - 0.25).abs() < 0.07, "{share}");
        for (i, &s) in swapped.iter().enumerate() {
            assert_eq!(v[i * 4], if s { -0.5 } else { 0.5 });
        }
    }
}
