//! The reconstruction loss of auto-decoding (reference section 5) and the host-side error
//! metric reported for every decoded scan.
//!
//! Both compare the generator's pre-drop inverse depth with a measured image on the measured
//! (valid) pixels only. Images are in network units (2 x_d - 1, no return = -1).

use burn::tensor::Tensor;

/// Inverse depth below this is treated as this (depth 145 m) inside the depth-relative term,
/// so a generator pixel heading to "infinitely far" gives a large but finite loss.
const MIN_X_D: f32 = 0.01;

/// One level of the loss: mean over valid pixels of |1 - x_gen / x_obs| (relative error of the
/// inverse depth) + |1 - d_gen / d_obs| (relative error of the depth, = |1 - x_obs / x_gen|).
///
/// # Shapes
/// - x_gen, x_obs, mask: `[batch, 1, H, W]`, x in (0, 1] (inverse depth), mask in {0, 1}
/// - -> `[batch]`
fn level_loss(x_gen: Tensor<4>, x_obs: Tensor<4>, mask: Tensor<4>) -> Tensor<1> {
    let b = x_gen.dims()[0];
    // Invalid pixels get x_obs = 1 so nothing divides by 0; the mask zeroes their terms.
    let x_obs = x_obs * mask.clone() - mask.clone().sub_scalar(1.0); // [batch, 1, H, W]
    let x_gen_safe = x_gen.clone().clamp_min(MIN_X_D); // [batch, 1, H, W]
    let inv = (x_gen / x_obs.clone()).sub_scalar(1.0).abs(); // [batch, 1, H, W]
    let depth = (x_obs / x_gen_safe).sub_scalar(1.0).abs(); // [batch, 1, H, W]
    let per_pixel = (inv + depth) * mask.clone(); // [batch, 1, H, W]
    let n = mask.reshape([b as i32, -1]).sum_dim(1).clamp_min(1.0); // [batch, 1]
    (per_pixel.reshape([b as i32, -1]).sum_dim(1) / n).reshape([b]) // [batch]
}

/// 2x2 masked mean pooling: the mean of the valid pixels of each 2x2 cell and whether the cell
/// had any (the "blurred pyramid" of the reference loss).
///
/// # Shapes
/// - x, mask: `[batch, 1, H, W]` -> `[batch, 1, H/2, W/2]` each
pub fn pool_masked(x: Tensor<4>, mask: Tensor<4>) -> (Tensor<4>, Tensor<4>) {
    let [b, c, h, w] = x.dims();
    let pool = |t: Tensor<4>| {
        t.reshape([b * c * (h / 2), 2, w / 2, 2])
            .sum_dim(3)
            .sum_dim(1)
            .reshape([b, c, h / 2, w / 2])
    };
    let count = pool(mask.clone()); // [batch, 1, H/2, W/2]
    let sum = pool(x * mask); // [batch, 1, H/2, W/2]
    let pooled = sum / count.clone().clamp_min(1.0);
    let mask = count.greater_elem(0.0).float();
    (pooled, mask)
}

/// The auto-decoding loss on the pre-drop inverse depth: [`level_loss`] at full resolution
/// plus `levels` masked 2x2-pooled levels (pooling generated and measured images with the same
/// measured-pixel weights), summed.
///
/// # Shapes
/// - x_gen_net, target_net: `[batch, 1, H, W]` network units; mask `[batch, 1, H, W]` in {0, 1}
/// - -> `[batch]`
pub fn reconstruction_loss(
    x_gen_net: Tensor<4>,
    target_net: Tensor<4>,
    mask: Tensor<4>,
    levels: usize,
) -> Tensor<1> {
    let mut x_gen = x_gen_net.add_scalar(1.0).mul_scalar(0.5); // [batch, 1, H, W] x_d
    let mut x_obs = target_net.add_scalar(1.0).mul_scalar(0.5); // [batch, 1, H, W]
    let mut mask = mask;
    let mut loss = level_loss(x_gen.clone(), x_obs.clone(), mask.clone());
    for _ in 0..levels {
        let [_, _, h, w] = x_gen.dims();
        if h < 2 || w < 2 || h % 2 != 0 || w % 2 != 0 {
            break;
        }
        let (g, _) = pool_masked(x_gen, mask.clone());
        let (o, m) = pool_masked(x_obs, mask);
        x_gen = g;
        x_obs = o;
        mask = m;
        loss = loss + level_loss(x_gen.clone(), x_obs.clone(), mask.clone());
    }
    loss
}

/// [`reconstruction_loss`] of one `h x w` image on the host, and its gradient with respect to
/// the generated image (network units): the loss of the hand-written pivotal tuning
/// ([`super::pivotal`]). Same function, pixel for pixel.
pub fn reconstruction_loss_grad(
    x_gen_net: &[f32],
    target_net: &[f32],
    mask: &[f32],
    (h, w): (usize, usize),
    levels: usize,
) -> (f32, Vec<f32>) {
    let to_x = |v: &[f32]| -> Vec<f32> { v.iter().map(|x| (x + 1.0) * 0.5).collect() };
    let mut pyramid = vec![HostLevel {
        x_gen: to_x(x_gen_net),
        x_obs: to_x(target_net),
        mask: mask.to_vec(),
        count: Vec::new(),
        size: (h, w),
    }];
    for _ in 0..levels {
        let (h, w) = pyramid.last().expect("level 0").size;
        if h < 2 || w < 2 || h % 2 != 0 || w % 2 != 0 {
            break;
        }
        let pooled = pyramid.last().expect("level 0").pooled();
        pyramid.push(pooled);
    }
    let mut loss = 0.0;
    let mut grad: Vec<f32> = Vec::new(); // of the current (coarser) level's x_gen
    for (l, level) in pyramid.iter().enumerate().rev() {
        let (value, mut g) = level.loss_grad();
        loss += value;
        if let Some(coarser) = pyramid.get(l + 1) {
            // Back through the masked mean: each pixel gets its cell's gradient / count.
            let (_, w) = level.size;
            for (k, gk) in g.iter_mut().enumerate() {
                let cell = (k / w / 2) * (w / 2) + (k % w) / 2;
                *gk += grad[cell] * level.mask[k] / coarser.count[cell].max(1.0);
            }
        }
        grad = g;
    }
    (loss, grad.iter().map(|g| 0.5 * g).collect())
}

/// One level of [`reconstruction_loss_grad`]'s pyramid.
struct HostLevel {
    x_gen: Vec<f32>,
    x_obs: Vec<f32>,
    mask: Vec<f32>,
    /// Measured pixels of the finer level in each cell (pooled levels only).
    count: Vec<f32>,
    size: (usize, usize),
}

impl HostLevel {
    /// [`pool_masked`] of both images.
    fn pooled(&self) -> HostLevel {
        let (h, w) = self.size;
        let (hp, wp) = (h / 2, w / 2);
        let mut sums = [
            vec![0.0f32; hp * wp],
            vec![0.0; hp * wp],
            vec![0.0; hp * wp],
        ];
        for k in 0..h * w {
            let cell = (k / w / 2) * wp + (k % w) / 2;
            let m = self.mask[k];
            sums[0][cell] += self.x_gen[k] * m;
            sums[1][cell] += self.x_obs[k] * m;
            sums[2][cell] += m;
        }
        let [g, o, count] = sums;
        let mean = |s: Vec<f32>| -> Vec<f32> {
            s.iter().zip(&count).map(|(s, c)| s / c.max(1.0)).collect()
        };
        HostLevel {
            x_gen: mean(g),
            x_obs: mean(o),
            mask: count
                .iter()
                .map(|c| f32::from(u8::from(*c > 0.0)))
                .collect(),
            count,
            size: (hp, wp),
        }
    }

    /// `level_loss` and its gradient with respect to x_gen.
    fn loss_grad(&self) -> (f32, Vec<f32>) {
        let sign = |v: f32| {
            if v > 0.0 {
                1.0
            } else if v < 0.0 {
                -1.0
            } else {
                0.0
            }
        };
        let n = self.mask.iter().sum::<f32>().max(1.0);
        let mut loss = 0.0f32;
        let grad = (self.x_gen.iter().zip(&self.x_obs).zip(&self.mask))
            .map(|((&g, &o), &m)| {
                if m == 0.0 {
                    return 0.0;
                }
                let safe = g.max(MIN_X_D);
                let (inv, depth) = (g / o - 1.0, o / safe - 1.0);
                loss += inv.abs() + depth.abs();
                let d_depth = if g > MIN_X_D {
                    -sign(depth) * o / (safe * safe)
                } else {
                    0.0
                };
                (sign(inv) / o + d_depth) / n
            })
            .collect();
        (loss / n, grad)
    }
}

/// The reported reconstruction error: mean over measured pixels of |d_gen - d_obs| / d_obs
/// (depths in meters), with the generated depth clamped to the valid range [1.45, 80] m.
/// `None` when nothing was measured.
pub fn relative_depth_error(depth_gen_m: &[f32], depth_obs_m: &[f32]) -> Option<f32> {
    let mut sum = 0.0f64;
    let mut n = 0usize;
    for (g, o) in depth_gen_m.iter().zip(depth_obs_m) {
        if *o > 0.0 {
            sum += f64::from(((g - o) / o).abs());
            n += 1;
        }
    }
    (n > 0).then(|| (sum / n as f64) as f32)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::util::tensor::{tensor_from, tensor_to_vec};
    use burn::tensor::Device;

    fn t(v: Vec<f32>, h: usize, w: usize) -> Tensor<4> {
        tensor_from(v, [1, 1, h, w], &Device::flex())
    }

    #[test]
    fn loss_is_zero_on_a_perfect_fit_and_ignores_unmeasured_pixels() {
        let obs = vec![0.0, -0.5, 0.5, -1.0];
        let mask = vec![1.0, 1.0, 1.0, 0.0];
        // The generator differs only where nothing was measured.
        let gen_ = vec![0.0, -0.5, 0.5, 0.9];
        let l = tensor_to_vec(reconstruction_loss(
            t(gen_, 2, 2),
            t(obs.clone(), 2, 2),
            t(mask.clone(), 2, 2),
            1,
        ));
        assert!(l[0].abs() < 1e-6, "{l:?}");
        // 10 % off in inverse depth on one of three measured pixels.
        let x_obs = 0.5f32; // network 0.0
        let x_gen = 0.55f32;
        let gen_ = vec![2.0 * x_gen - 1.0, -0.5, 0.5, 0.9];
        let l = tensor_to_vec(reconstruction_loss(
            t(gen_, 2, 2),
            t(obs, 2, 2),
            t(mask, 2, 2),
            0,
        ));
        let expected = ((x_gen / x_obs - 1.0).abs() + (x_obs / x_gen - 1.0).abs()) / 3.0;
        assert!((l[0] - expected).abs() < 1e-5, "{} vs {expected}", l[0]);
    }

    #[test]
    fn host_loss_and_gradient_match_autodiff() {
        let (h, w) = (4, 8);
        let wave = |a: f32, b: f32| (0..h * w).map(move |k| (k as f32 * a + b).sin() * 0.6);
        let gen_: Vec<f32> = wave(0.7, 0.3).collect();
        let obs: Vec<f32> = wave(0.4, 1.1).collect();
        let mask: Vec<f32> = (0..h * w)
            .map(|k| f32::from(u8::from(k % 3 != 1)))
            .collect();
        let ad = Device::flex().autodiff();
        let x = tensor_from(gen_.clone(), [1, 1, h, w], &ad).require_grad();
        let obs_t = tensor_from(obs.clone(), [1, 1, h, w], &ad);
        let mask_t = tensor_from(mask.clone(), [1, 1, h, w], &ad);
        let loss = reconstruction_loss(x.clone(), obs_t, mask_t, 2).sum();
        let want = loss.clone().inner().into_scalar::<f32>();
        let want_grad = tensor_to_vec(x.grad(&loss.backward()).expect("a gradient"));
        let (got, grad) = reconstruction_loss_grad(&gen_, &obs, &mask, (h, w), 2);
        assert!(
            (got - want).abs() < 1e-5 * want.abs().max(1.0),
            "{got} vs {want}"
        );
        for (g, e) in grad.iter().zip(&want_grad) {
            assert!((g - e).abs() < 1e-5, "{g} vs {e}");
        }
    }

    #[test]
    fn relative_depth_error_uses_measured_pixels() {
        let e = relative_depth_error(&[11.0, 5.0, 3.0], &[10.0, 0.0, 3.0]).unwrap();
        assert!((e - 0.05).abs() < 1e-6);
        assert!(relative_depth_error(&[1.0], &[0.0]).is_none());
    }
}
