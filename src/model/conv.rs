//! Circular convolutions on range images (`[batch, ch, H, W]`): padding that wraps along
//! azimuth and replicates along elevation, [1,3,3,1] blur-downsampling, the equalised-lr
//! convolution of the discriminator and the encoder, and the modulated 3x3 convolution of the
//! generator's local path. Convolutions run as one matrix product over shifted views (im2col),
//! whose gradients are matrix products too.

use burn::config::Config;
use burn::module::{Module, Param};
use burn::tensor::module::conv2d;
use burn::tensor::ops::ConvOptions;
use burn::tensor::{Device, Tensor, TensorData};

use super::layers::{EqualLinear, EqualLinearConfig, lrelu_gain};
use crate::util::rng::Rng;

/// Pad `[batch, ch, H, W]` by `p` on every side: circular along W, replicate along H.
pub fn pad_circular(x: Tensor<4>, p: usize) -> Tensor<4> {
    if p == 0 {
        return x;
    }
    let [_, _, h, w] = x.dims();
    let left = x.clone().narrow(3, w - p, p);
    let right = x.clone().narrow(3, 0, p);
    let x = Tensor::cat(vec![left, x, right], 3);
    let top = x.clone().narrow(2, 0, 1).repeat_dim(2, p);
    let bottom = x.clone().narrow(2, h - 1, 1).repeat_dim(2, p);
    Tensor::cat(vec![top, x, bottom], 2)
}

/// 2x blur-downsampling with the [1,3,3,1] filter along both axes: circular along W, replicate
/// along H. One depthwise 4x4 stride-2 convolution over the padded image (each channel as its
/// own image), which costs half the time of the same filter built from shifted copies.
///
/// # Shapes
/// - x: `[batch, ch, H, W]` -> `[batch, ch, H/2, W/2]`
pub fn downsample2x(x: Tensor<4>) -> Tensor<4> {
    let [b, c, h, w] = x.dims();
    let taps = [1.0f32, 3.0, 3.0, 1.0];
    let kernel: Vec<f32> = taps
        .iter()
        .flat_map(|a| taps.iter().map(move |b| a * b / 64.0))
        .collect();
    let kernel = Tensor::<4>::from_data(TensorData::new(kernel, [1, 1, 4, 4]), &x.device());
    let x = pad_circular(x.reshape([b * c, 1, h, w]), 1); // [batch*ch, 1, H+2, W+2]
    let y = conv2d(x, kernel, None, ConvOptions::new([2, 2], [0, 0], [1, 1], 1)); // [batch*ch, 1, H/2, W/2]
    y.reshape([b, c, h / 2, w / 2])
}

#[derive(Config, Debug)]
pub struct EqualConvConfig {
    pub d_input: usize,
    pub d_output: usize,
    #[config(default = 3)]
    pub kernel: usize,
    #[config(default = true)]
    pub bias: bool,
    #[config(default = true)]
    pub activate: bool,
}

#[derive(Module, Debug)]
pub struct EqualConv {
    /// `[out, in, k, k]`
    pub weight: Param<Tensor<4>>,
    pub bias: Option<Param<Tensor<1>>>,
    #[module(skip)]
    pub weight_gain: f32,
    #[module(skip)]
    pub activate: bool,
}

impl EqualConvConfig {
    pub fn init(&self, rng: &mut Rng, device: &Device) -> EqualConv {
        let k = self.kernel;
        EqualConv {
            weight: Param::from_tensor(
                rng.normal_tensor([self.d_output, self.d_input, k, k], device),
            ),
            bias: self
                .bias
                .then(|| Param::from_tensor(Tensor::zeros([self.d_output], device))),
            weight_gain: 1.0 / ((self.d_input * k * k) as f32).sqrt(),
            activate: self.activate,
        }
    }
}

impl EqualConv {
    /// # Shapes
    /// - x: `[batch, in, H, W]` -> `[batch, out, H, W]`
    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let k = self.weight.dims()[2];
        let weight = self.weight.val().mul_scalar(self.weight_gain);
        let bias = self.bias.as_ref().map(|b| b.val());
        let y = conv_as_matmul(pad_circular(x, k / 2), weight, bias);
        if self.activate { lrelu_gain(y) } else { y }
    }
}

/// A stride-1 convolution of an already padded input, written as one matrix product over
/// its `k x k` shifted views (im2col). Same result as `conv2d`, but its gradients are matrix
/// products too: the CPU backend computes `conv2d`'s weight gradient as a convolution with
/// an image-sized kernel, which took a third of a training step.
///
/// # Shapes
/// - x: `[batch, in, H + k - 1, W + k - 1]`, weight: `[out, in, k, k]` -> `[batch, out, H, W]`
fn conv_as_matmul(x: Tensor<4>, weight: Tensor<4>, bias: Option<Tensor<1>>) -> Tensor<4> {
    let [b, c, hp, wp] = x.dims();
    let [o, _, k, _] = weight.dims();
    let (h, w) = (hp + 1 - k, wp + 1 - k);
    let cols = if k == 1 {
        x.reshape([b, c, h * w])
    } else {
        // Each channel as its own image through a constant one-hot kernel: output t holds
        // the view shifted by (t / k, t % k), ordered (channel, dy, dx) like the weight's last
        // three axes. The kernel is a constant, so the backward pass is one transposed
        // convolution, not a zeroed padded-size buffer per view (4 % more images/s).
        let mut one_hot = vec![0f32; k * k * k * k];
        for t in 0..k * k {
            one_hot[t * k * k + t] = 1.0;
        }
        let one_hot =
            Tensor::<4>::from_data(TensorData::new(one_hot, [k * k, 1, k, k]), &x.device());
        let options = ConvOptions::new([1, 1], [0, 0], [1, 1], 1);
        conv2d(x.reshape([b * c, 1, hp, wp]), one_hot, None, options).reshape([b, c * k * k, h * w])
    };
    let y = weight
        .reshape([1, o, c * k * k])
        .expand([b, o, c * k * k])
        .matmul(cols); // [batch, out, H*W]
    let y = match bias {
        Some(bias) => y + bias.reshape([1, o, 1]),
        None => y,
    };
    y.reshape([b, o, h, w])
}

/// The generator's local path: a modulated 3x3 circular convolution (StyleGAN2 modulation and
/// demodulation) added to a synthesis block's features through a learned gain that starts at
/// zero, so a generator gains the path without changing what it draws. The implicit layers
/// see one pixel at a time; this path lets neighbouring pixels shape each other (the edge of a
/// car, a pole one column wide).
#[derive(Config, Debug)]
pub struct LocalConvConfig {
    pub channels: usize,
    /// Width of the latent w.
    pub d_style: usize,
}

#[derive(Module, Debug)]
pub struct LocalConv {
    /// w -> per-input-channel style s (bias initialised to 1).
    pub affine: EqualLinear,
    /// `[ch, ch, 3, 3]`, N(0,1), scaled by 1/sqrt(9 ch) at run time.
    pub weight: Param<Tensor<4>>,
    /// `[ch]`
    pub bias: Param<Tensor<1>>,
    /// `[1]` the residual gain, 0 at initialisation.
    pub gain: Param<Tensor<1>>,
    #[module(skip)]
    pub weight_gain: f32,
}

impl LocalConvConfig {
    pub fn init(&self, rng: &mut Rng, device: &Device) -> LocalConv {
        let c = self.channels;
        LocalConv {
            affine: EqualLinearConfig::new(self.d_style, c)
                .with_bias_init(1.0)
                .init(rng, device),
            weight: Param::from_tensor(rng.normal_tensor([c, c, 3, 3], device)),
            bias: Param::from_tensor(Tensor::zeros([c], device)),
            gain: Param::from_tensor(Tensor::zeros([1], device)),
            weight_gain: 1.0 / ((9 * c) as f32).sqrt(),
        }
    }
}

impl LocalConv {
    /// `x + gain * lrelu(demodulated conv3x3(x * s) + bias)` on a channels-last feature map.
    ///
    /// # Shapes
    /// - x: `[batch, H*W, ch]`, w: `[batch, d_style]` -> `[batch, H*W, ch]`
    pub fn forward(&self, x: Tensor<3>, height: usize, width: usize, w: Tensor<2>) -> Tensor<3> {
        let [b, n, c] = x.dims();
        let s = self.affine.forward(w); // [batch, ch]
        let weight = self.weight.val().mul_scalar(self.weight_gain); // [ch, ch, 3, 3]
        let image = (x.clone() * s.clone().unsqueeze_dim::<3>(1))
            .reshape([b, height, width, c])
            .permute([0, 3, 1, 2]); // [batch, ch, H, W]
        let y = conv_as_matmul(pad_circular(image, 1), weight.clone(), None); // [batch, ch, H, W]
        let energy = weight.powi_scalar(2).sum_dim(3).sum_dim(2).reshape([c, c]); // [out, in]
        let demod = s
            .powi_scalar(2)
            .matmul(energy.transpose())
            .add_scalar(1e-8)
            .sqrt()
            .recip(); // [batch, out]
        let y = y * demod.reshape([b, c, 1, 1]) + self.bias.val().reshape([1, c, 1, 1]);
        let y = lrelu_gain(y).permute([0, 2, 3, 1]).reshape([b, n, c]); // [batch, H*W, ch]
        x + y * self.gain.val().reshape([1, 1, 1])
    }
}

#[cfg(test)]
mod tests {
    use super::super::layers::roll;
    use super::*;
    use crate::util::tensor::tensor_to_vec;

    #[test]
    fn downsample_keeps_constants_and_matches_filter() {
        let dev = Device::flex();
        let x = Tensor::<4>::ones([1, 1, 4, 8], &dev);
        let y = downsample2x(x);
        assert_eq!(y.dims(), [1, 1, 2, 4]);
        assert!(tensor_to_vec(y).iter().all(|v| (v - 1.0).abs() < 1e-6));
        // One row, columns 0..8 as values: out[0] = (x[7] + 3x[0] + 3x[1] + x[2]) / 8 (circular)
        let v: Vec<f32> = (0..16).map(|i| (i % 8) as f32).collect();
        let x = crate::util::tensor::tensor_from(v, [1, 1, 2, 8], &dev);
        let y = tensor_to_vec(downsample2x(x));
        assert!((y[0] - (7.0 + 0.0 + 3.0 + 2.0) / 8.0).abs() < 1e-6, "{y:?}");
    }

    #[test]
    fn downsample_matches_the_filter_written_out_on_random_data() {
        let (h, w) = (6, 10);
        let mut rng = Rng::new(8);
        let x: Vec<f32> = rng.normal_vec(2 * h * w);
        let y = tensor_to_vec(downsample2x(crate::util::tensor::tensor_from(
            x.clone(),
            [1, 2, h, w],
            &Device::flex(),
        )));
        let taps = [1.0f32, 3.0, 3.0, 1.0];
        for c in 0..2 {
            for i in 0..h / 2 {
                for j in 0..w / 2 {
                    let mut want = 0.0;
                    for (a, ta) in taps.iter().enumerate() {
                        let r = (2 * i + a).saturating_sub(1).min(h - 1);
                        for (b, tb) in taps.iter().enumerate() {
                            let col = (2 * j + b + w - 1) % w;
                            want += ta * tb / 64.0 * x[c * h * w + r * w + col];
                        }
                    }
                    let got = y[c * (h / 2) * (w / 2) + i * (w / 2) + j];
                    assert!((got - want).abs() < 1e-5, "({c},{i},{j}): {got} vs {want}");
                }
            }
        }
    }

    #[test]
    fn circular_conv_is_shift_equivariant_along_azimuth() {
        let dev = Device::flex();
        let mut rng = Rng::new(3);
        let conv = EqualConvConfig::new(2, 3).init(&mut rng, &dev);
        let x = rng.normal_tensor([1, 2, 4, 8], &dev);
        let a = roll(conv.forward(x.clone()), 1, 3);
        let b = conv.forward(roll(x, 1, 3));
        assert!((a - b).abs().max().into_scalar::<f32>() < 1e-5);
    }

    #[test]
    fn conv_as_matmul_matches_conv2d_and_its_gradients() {
        let dev = Device::flex().autodiff();
        let mut rng = Rng::new(5);
        for k in [1, 3] {
            let x = rng.normal_tensor([2, 3, 5 + k - 1, 9 + k - 1], &dev);
            let weight = rng.normal_tensor([4, 3, k, k], &dev);
            let bias = rng.normal_tensor([4], &dev);
            let upstream = rng.normal_tensor([2, 4, 5, 9], &dev);
            let run = |im2col: bool| {
                let (x, weight, bias) = (
                    x.clone().require_grad(),
                    weight.clone().require_grad(),
                    bias.clone().require_grad(),
                );
                let y = if im2col {
                    conv_as_matmul(x.clone(), weight.clone(), Some(bias.clone()))
                } else {
                    let options = ConvOptions::new([1, 1], [0, 0], [1, 1], 1);
                    conv2d(x.clone(), weight.clone(), Some(bias.clone()), options)
                };
                let grads = (y.clone() * upstream.clone()).sum().backward();
                let grad = |t: Option<Tensor<4>>| tensor_to_vec(t.unwrap());
                (
                    tensor_to_vec(y.inner()),
                    grad(x.grad(&grads)),
                    grad(weight.grad(&grads)),
                    tensor_to_vec(bias.grad(&grads).unwrap()),
                )
            };
            let (a, b) = (run(true), run(false));
            let close = |p: &[f32], q: &[f32]| {
                p.len() == q.len() && p.iter().zip(q).all(|(p, q)| (p - q).abs() < 1e-4)
            };
            assert!(close(&a.0, &b.0), "output, k = {k}");
            assert!(close(&a.1, &b.1), "input gradient, k = {k}");
            assert!(close(&a.2, &b.2), "weight gradient, k = {k}");
            assert!(close(&a.3, &b.3), "bias gradient, k = {k}");
        }
    }

    #[test]
    fn local_path_starts_as_the_identity_and_then_mixes_neighbours() {
        let dev = Device::flex();
        let mut rng = Rng::new(11);
        let mut local = LocalConvConfig::new(3, 4).init(&mut rng, &dev);
        let (h, w) = (4, 8);
        let x = rng.normal_tensor([2, h * w, 3], &dev);
        let style = rng.normal_tensor([2, 4], &dev);
        let same = local.forward(x.clone(), h, w, style.clone());
        assert_eq!(tensor_to_vec(same), tensor_to_vec(x.clone()));
        local.gain = Param::from_tensor(Tensor::ones([1], &dev));
        // One pixel changed: the output moves at its 3 x 3 neighbours (wrapping along azimuth)
        // and nowhere else.
        let mut bumped = tensor_to_vec(x.clone());
        let (r, col) = (1, 0);
        bumped[((r * w + col) * 3)..((r * w + col) * 3 + 3)].fill(5.0);
        let bumped = crate::util::tensor::tensor_from(bumped, [2, h * w, 3], &dev);
        let diff = tensor_to_vec(
            (local.forward(bumped, h, w, style.clone()) - local.forward(x, h, w, style))
                .abs()
                .sum_dim(2),
        );
        for i in 0..h {
            for j in 0..w {
                let near = i.abs_diff(r) <= 1 && (j == col || j == 1 || j == w - 1);
                let d = diff[i * w + j];
                assert_eq!(d > 1e-6, near, "pixel ({i}, {j}): change {d}");
            }
        }
    }
}
