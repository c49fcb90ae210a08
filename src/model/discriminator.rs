//! The discriminator: a residual CNN on measured range images with circular padding along
//! azimuth (replicate along elevation), [1,3,3,1] blur-downsampling, minibatch standard deviation
//! and a linear head giving one logit per image. Shared by all three architectures.

use burn::config::Config;
use burn::module::{Module, Param};
use burn::tensor::module::conv2d;
use burn::tensor::ops::ConvOptions;
use burn::tensor::{Device, Tensor, TensorData};

use super::layers::{EqualLinear, EqualLinearConfig, lrelu_gain, roll, shift_replicate};
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

/// Residual block: conv 3x3 -> blur-downsample -> conv 3x3, plus a downsampled 1x1 skip.
#[derive(Config, Debug)]
pub struct ResBlockConfig {
    pub d_input: usize,
    pub d_output: usize,
}

#[derive(Module, Debug)]
pub struct ResBlock {
    pub conv0: EqualConv,
    pub conv1: EqualConv,
    pub skip: EqualConv,
}

impl ResBlockConfig {
    pub fn init(&self, rng: &mut Rng, device: &Device) -> ResBlock {
        ResBlock {
            conv0: EqualConvConfig::new(self.d_input, self.d_input).init(rng, device),
            conv1: EqualConvConfig::new(self.d_input, self.d_output).init(rng, device),
            skip: EqualConvConfig::new(self.d_input, self.d_output)
                .with_kernel(1)
                .with_bias(false)
                .with_activate(false)
                .init(rng, device),
        }
    }
}

impl ResBlock {
    /// # Shapes
    /// - x: `[batch, in, H, W]` -> `[batch, out, H/2, W/2]`
    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let skip = self.skip.forward(downsample2x(x.clone())); // [batch, out, H/2, W/2]
        let y = self.conv0.forward(x); // [batch, in, H, W]
        let y = self.conv1.forward(downsample2x(y)); // [batch, out, H/2, W/2]
        (y + skip).mul_scalar(std::f32::consts::FRAC_1_SQRT_2)
    }
}

/// Discriminator (reference section 4). Defaults are the paper's widths.
#[derive(Config, Debug)]
pub struct DiscriminatorConfig {
    /// Input height and width (the linear head depends on them).
    #[config(default = 64)]
    pub height: usize,
    #[config(default = 512)]
    pub width: usize,
    /// Channels after the input layer and after each residual block.
    #[config(default = "vec![32, 64, 128, 256, 512]")]
    pub channels: Vec<usize>,
    /// Pixels per side folded into channels before the input layer: 1 starts at full
    /// resolution; 2 folds each 2 x 2 block into 4x the channels (lossless), so every
    /// convolution runs at half resolution or below.
    #[config(default = 1)]
    pub stem: usize,
    /// Minibatch-stddev group size.
    #[config(default = 4)]
    pub mbstd_group: usize,
    /// The input as two copies blurred [1,2,1] along elevation and along azimuth; false: the
    /// image itself, twice (the same weights' shapes).
    #[config(default = true)]
    pub input_blur: bool,
    #[config(default = 1)]
    pub seed: u64,
}

#[derive(Module, Debug)]
pub struct Discriminator {
    pub from_input: EqualConv,
    pub blocks: Vec<ResBlock>,
    pub conv_out: EqualConv,
    pub fc: EqualLinear,
    pub out: EqualLinear,
    #[module(skip)]
    pub mbstd_group: usize,
    #[module(skip)]
    pub stem: usize,
    #[module(skip)]
    pub input_blur: bool,
}

impl DiscriminatorConfig {
    /// The CPU configuration chosen by measurement (docs/model_benchmarks.md).
    pub fn cpu() -> Self {
        Self::new().with_channels(vec![8, 16, 32, 64, 128])
    }

    /// [`Self::cpu`] without its full-resolution block: a 2 x 2 stem, then the same
    /// widths from 16 channels at half resolution, and the same head.
    pub fn cpu_half_resolution() -> Self {
        Self::new()
            .with_stem(2)
            .with_channels(vec![16, 32, 64, 128])
    }

    pub fn init(&self, device: &Device) -> Discriminator {
        let mut rng = Rng::new(self.seed);
        let c = &self.channels;
        let n_down = c.len() - 1;
        let stem = self.stem.max(1);
        let fold = stem << n_down;
        assert!(
            self.height.is_multiple_of(fold) && self.width.is_multiple_of(fold),
            "discriminator input must divide by {fold}"
        );
        let last = c[c.len() - 1];
        let (h, w) = (self.height / fold, self.width / fold);
        Discriminator {
            from_input: EqualConvConfig::new(2 * stem * stem, c[0])
                .with_kernel(1)
                .init(&mut rng, device),
            blocks: (0..n_down)
                .map(|i| ResBlockConfig::new(c[i], c[i + 1]).init(&mut rng, device))
                .collect(),
            conv_out: EqualConvConfig::new(last + 1, last).init(&mut rng, device),
            fc: EqualLinearConfig::new(last * h * w, last)
                .with_activate(true)
                .init(&mut rng, device),
            out: EqualLinearConfig::new(last, 1).init(&mut rng, device),
            mbstd_group: self.mbstd_group,
            stem,
            input_blur: self.input_blur,
        }
    }
}

impl Discriminator {
    /// # Shapes
    /// - x: `[batch, 1, H, W]` measured image in network units -> logits `[batch, 1]`
    pub fn forward(&self, x: Tensor<4>) -> Tensor<2> {
        let b = x.dims()[0];
        let pair = if self.input_blur {
            let horiz =
                (roll(x.clone(), 1, 3) + roll(x.clone(), -1, 3) + x.clone().mul_scalar(2.0))
                    .div_scalar(4.0); // [batch, 1, H, W]
            let vert = (shift_replicate(x.clone(), 1, 2)
                + shift_replicate(x.clone(), -1, 2)
                + x.mul_scalar(2.0))
            .div_scalar(4.0); // [batch, 1, H, W]
            vec![vert, horiz]
        } else {
            vec![x.clone(), x]
        };
        let x = space_to_depth(Tensor::cat(pair, 1), self.stem); // [batch, 2*s*s, H/s, W/s]
        let mut y = self.from_input.forward(x); // [batch, c0, H/s, W/s]
        for block in &self.blocks {
            y = block.forward(y); // [batch, c, h, w]
        }
        let y = minibatch_stddev(y, self.mbstd_group); // [batch, c + 1, h, w]
        let y = self.conv_out.forward(y); // [batch, c, h, w]
        let y = y.reshape([b as i64, -1]); // [batch, c*h*w]
        self.out.forward(self.fc.forward(y)) // [batch, 1]
    }
}

/// Folds each `s x s` block of pixels into channels (channel-major, then row and column
/// within the block); `s = 1` is the identity.
///
/// # Shapes
/// - x: `[batch, ch, H, W]` -> `[batch, ch*s*s, H/s, W/s]`
pub fn space_to_depth(x: Tensor<4>, s: usize) -> Tensor<4> {
    if s <= 1 {
        return x;
    }
    let [b, c, h, w] = x.dims();
    x.reshape([b, c, h / s, s, w / s, s]) // [batch, ch, H/s, s, W/s, s]
        .permute([0, 1, 3, 5, 2, 4]) // [batch, ch, s, s, H/s, W/s]
        .reshape([b, c * s * s, h / s, w / s])
}

/// Append the mean (over channels and pixels) of the per-group standard deviation as a channel.
///
/// # Shapes
/// - x: `[batch, ch, H, W]` -> `[batch, ch + 1, H, W]`
pub fn minibatch_stddev(x: Tensor<4>, group: usize) -> Tensor<4> {
    let [b, c, h, w] = x.dims();
    let mut g = group.min(b).max(1);
    while b % g != 0 {
        g -= 1;
    }
    let y = x.clone().reshape([g, b / g, c, h, w]); // [G, M, ch, H, W]
    let y = y.clone() - y.mean_dim(0); // [G, M, ch, H, W]
    let std = y.powi_scalar(2).mean_dim(0).add_scalar(1e-8).sqrt(); // [1, M, ch, H, W]
    let s = std.reshape([b / g, c * h * w]).mean_dim(1); // [M, 1]
    let s = s.reshape([1, b / g]).repeat_dim(0, g).reshape([b, 1, 1, 1]); // [batch, 1, 1, 1]
    let s = s.repeat_dim(2, h).repeat_dim(3, w); // [batch, 1, H, W]
    Tensor::cat(vec![x, s], 1)
}

#[cfg(test)]
mod tests {
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
    fn space_to_depth_folds_each_block_into_channels() {
        let v: Vec<f32> = (0..16).map(|i| i as f32).collect();
        let x = crate::util::tensor::tensor_from(v, [1, 1, 2, 8], &Device::flex());
        let y = space_to_depth(x, 2);
        assert_eq!(y.dims(), [1, 4, 1, 4]);
        // Channel (r, c) of the block holds pixel (r, 2j + c) of column block j.
        assert_eq!(
            tensor_to_vec(y),
            [
                0., 2., 4., 6., 1., 3., 5., 7., 8., 10., 12., 14., 9., 11., 13., 15.
            ]
        );
    }

    #[test]
    fn half_resolution_discriminator_gives_one_logit_per_image() {
        let dev = Device::flex();
        let d = DiscriminatorConfig::cpu_half_resolution().init(&dev);
        let full = DiscriminatorConfig::cpu().init(&dev);
        let x = Rng::new(4).normal_tensor([4, 1, 64, 512], &dev);
        assert_eq!(d.forward(x.clone()).dims(), [4, 1]);
        // The same head: the last feature map is 4 x 32 in both.
        assert_eq!(d.fc.weight.val().dims(), full.fc.weight.val().dims());
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
    fn discriminator_shapes_and_gradients() {
        let dev = Device::flex().autodiff();
        let d = DiscriminatorConfig::new()
            .with_height(8)
            .with_width(32)
            .with_channels(vec![4, 8, 8])
            .init(&dev);
        let x = Rng::new(1)
            .normal_tensor([4, 1, 8, 32], &dev)
            .require_grad();
        let logits = d.forward(x.clone());
        assert_eq!(logits.dims(), [4, 1]);
        let grads = logits.sum().backward();
        assert!(x.grad(&grads).is_some());
        assert!(d.fc.weight.val().grad(&grads).is_some());
        assert!(d.blocks[0].conv0.weight.val().grad(&grads).is_some());
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
    fn minibatch_stddev_sees_the_batch() {
        let dev = Device::flex();
        let same = Tensor::<4>::ones([4, 2, 2, 2], &dev);
        let y = minibatch_stddev(same, 4);
        let extra = tensor_to_vec(y.narrow(1, 2, 1));
        assert!(extra.iter().all(|v| *v < 1e-3));
        let mut rng = Rng::new(2);
        let y = minibatch_stddev(rng.normal_tensor([4, 2, 2, 2], &dev), 4);
        let extra = tensor_to_vec(y.narrow(1, 2, 1));
        assert!(extra.iter().all(|v| *v > 0.1));
    }
}
