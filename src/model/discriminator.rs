//! The discriminator: a residual CNN on measured range images with circular padding along
//! azimuth (replicate along elevation), [1,3,3,1] blur-downsampling, minibatch standard deviation
//! and a linear head giving one logit per image. Shared by all three architectures.

use burn::config::Config;
use burn::module::{Module, Param};
use burn::tensor::{Device, Tensor};

use super::conv::{EqualConv, EqualConvConfig, downsample2x};
use super::layers::{EqualLinear, EqualLinearConfig, roll, shift_replicate};
use crate::lidar::range_image::column_azimuth;
use crate::util::rng::Rng;
use crate::util::tensor::{tensor_from, tensor_to_vec};

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
    /// Each column's azimuth (sine and cosine) as two more input channels: a discriminator
    /// of windows of the turn learns what belongs where (ahead, behind, to the sides).
    #[config(default = false)]
    pub azimuth_input: bool,
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
    /// Refuses sizes that cannot be built or would not fit in memory.
    pub fn check(&self) -> anyhow::Result<()> {
        use crate::util::bounds;
        bounds::size("discriminator.height", self.height, 1..=512)?;
        bounds::size("discriminator.width", self.width, 1..=16384)?;
        bounds::sizes("discriminator.channels", &self.channels, 1..=8, 1..=4096)?;
        bounds::size("discriminator.stem", self.stem, 1..=8)?;
        bounds::size("discriminator.mbstd_group", self.mbstd_group, 1..=64)
    }

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

    /// Image channels: the measured image, and the azimuth's two where it reads them.
    fn input_channels(&self) -> usize {
        if self.azimuth_input { 3 } else { 1 }
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
            from_input: EqualConvConfig::new(2 * self.input_channels() * stem * stem, c[0])
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
        self.forward_at(x, None)
    }

    /// [`Discriminator::forward`] for a discriminator that reads each column's azimuth
    /// (`azimuth_input`): `azimuth` holds its sine and cosine ([`column_azimuths`]).
    ///
    /// # Shapes
    /// - x: `[batch, 1, H, W]`, azimuth: `[batch, 2, 1, W]` -> logits `[batch, 1]`
    pub fn forward_at(&self, x: Tensor<4>, azimuth: Option<Tensor<4>>) -> Tensor<2> {
        self.judge(self.features_at(x, azimuth))
    }

    /// The last residual block's features of `x`, which [`Discriminator::judge`] reads (and
    /// a self-supervised decoder rebuilds the scan from).
    ///
    /// # Shapes
    /// - x: `[batch, 1, H, W]`, azimuth: `[batch, 2, 1, W]` -> `[batch, c, H/fold, W/fold]`
    pub fn features_at(&self, x: Tensor<4>, azimuth: Option<Tensor<4>>) -> Tensor<4> {
        let [_, _, h, _] = x.dims();
        let x = match azimuth {
            Some(a) => Tensor::cat(vec![x, a.repeat_dim(2, h)], 1), // [batch, 3, H, W]
            None => x,
        };
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
        y
    }

    /// The logits of the last features ([`Discriminator::features_at`]): minibatch standard
    /// deviation, a convolution and the linear head.
    ///
    /// # Shapes
    /// - features: `[batch, c, h, w]` -> logits `[batch, 1]`
    pub fn judge(&self, features: Tensor<4>) -> Tensor<2> {
        let b = features.dims()[0];
        let y = minibatch_stddev(features, self.mbstd_group); // [batch, c + 1, h, w]
        let y = self.conv_out.forward(y); // [batch, c, h, w]
        let y = y.reshape([b as i64, -1]); // [batch, c*h*w]
        self.out.forward(self.fc.forward(y)) // [batch, 1]
    }
}

impl Discriminator {
    /// A discriminator of windows that starts from this whole-turn one. `windows` is a fresh
    /// discriminator of the same channels and stem at the window's width, reading the
    /// azimuth; `rows` is the height of the last feature map (the input's over its fold).
    /// The convolutions carry over, since they are the same at any width. The input layer
    /// reads the image as before and the azimuth through zeros. The head reads each window
    /// position as the sum of the turn's positions that fall on it when the turn is tiled
    /// with windows: a window is first judged as if every window of the turn looked like it.
    pub fn into_windows(self, windows: Discriminator, rows: usize) -> Discriminator {
        let stem2 = self.stem * self.stem;
        // Input channels: the [vertical, horizontal] blurred copies of [image (, azimuth
        // sine, cosine)], each channel folded into stem^2.
        let per_copy = windows.from_input.weight.dims()[1] / (2 * stem2);
        let from_input = carry_weights(
            &self.from_input.weight,
            self.from_input.weight_gain,
            &windows.from_input.weight,
            windows.from_input.weight_gain,
            |k| (k / stem2) * per_copy * stem2 + k % stem2,
        );
        // The head's inputs: (channel, row, column) of the last feature map, flattened.
        let c = self.conv_out.weight.dims()[0];
        let whole_cols = self.fc.weight.dims()[1] / (c * rows);
        let window_cols = windows.fc.weight.dims()[1] / (c * rows);
        let fc = carry_weights(
            &self.fc.weight,
            self.fc.weight_gain,
            &windows.fc.weight,
            windows.fc.weight_gain,
            |k| (k / whole_cols) * window_cols + (k % whole_cols) % window_cols,
        );
        // The window's layers keep their own gains, which the carried weights are scaled to.
        Discriminator {
            from_input: EqualConv {
                weight: from_input,
                bias: self.from_input.bias,
                ..windows.from_input
            },
            blocks: self.blocks,
            conv_out: self.conv_out,
            fc: EqualLinear {
                weight: fc,
                bias: self.fc.bias,
                ..windows.fc
            },
            out: self.out,
            ..windows
        }
    }
}

/// `to`'s weights (`[out, in, ..]`, scaled by `to_gain` in use) holding what `from`'s
/// (scaled by `from_gain`) computed: input `k` of `from` adds to input `map(k)` of `to`;
/// inputs nothing maps to read zeros.
fn carry_weights<const D: usize>(
    from: &Param<Tensor<D>>,
    from_gain: f32,
    to: &Param<Tensor<D>>,
    to_gain: f32,
    map: impl Fn(usize) -> usize,
) -> Param<Tensor<D>> {
    let (from_dims, to_dims) = (from.dims(), to.dims());
    let inner: usize = from_dims[2..].iter().product();
    let (from_in, to_in) = (from_dims[1], to_dims[1]);
    let values = tensor_to_vec(from.val());
    let mut out = vec![0f32; to_dims.iter().product()];
    let scale = from_gain / to_gain;
    for o in 0..from_dims[0] {
        for k in 0..from_in {
            let src = &values[(o * from_in + k) * inner..][..inner];
            let dst = &mut out[(o * to_in + map(k)) * inner..][..inner];
            dst.iter_mut().zip(src).for_each(|(d, s)| *d += s * scale);
        }
    }
    Param::from_tensor(tensor_from(out, to_dims, &to.device()))
}

/// Sine and cosine of the azimuth of each column of windows of a turn of `full_width`
/// columns: window `i` holds columns `start[i]..start[i] + width` (circular).
///
/// # Shapes
/// -> `[start.len(), 2, 1, width]`
pub fn column_azimuths(
    start: &[usize],
    width: usize,
    full_width: usize,
    device: &Device,
) -> Tensor<4> {
    let mut v = Vec::with_capacity(start.len() * 2 * width);
    for &c in start {
        let theta = |j: usize| column_azimuth((c + j) % full_width, full_width);
        v.extend((0..width).map(|j| theta(j).sin()));
        v.extend((0..width).map(|j| theta(j).cos()));
    }
    tensor_from(v, [start.len(), 2, 1, width], device)
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
    fn a_window_discriminator_reads_where_the_window_is() {
        let dev = Device::flex();
        let d = DiscriminatorConfig::new()
            .with_height(8)
            .with_width(16)
            .with_channels(vec![4, 8])
            .with_azimuth_input(true)
            .init(&dev);
        let x = Rng::new(2).normal_tensor([2, 1, 8, 16], &dev);
        let ahead = column_azimuths(&[56, 56], 16, 64, &dev);
        let behind = column_azimuths(&[24, 24], 16, 64, &dev);
        let a = tensor_to_vec(d.forward_at(x.clone(), Some(ahead)));
        let b = tensor_to_vec(d.forward_at(x, Some(behind)));
        assert_eq!(a.len(), 2);
        assert!((a[0] - b[0]).abs() > 1e-4, "{a:?} {b:?}");
        // The columns wrap around the seam: the window at 56 ends on columns 0..8.
        let az = tensor_to_vec(column_azimuths(&[56], 16, 64, &dev));
        let expected = column_azimuth(3, 64).sin();
        assert!((az[8 + 3] - expected).abs() < 1e-6);
    }

    /// On a turn made of one window repeated, the window discriminator started from the
    /// whole-turn one judges the window exactly as that one judges the turn.
    #[test]
    fn a_window_discriminator_starts_as_the_whole_turns_one() {
        let dev = Device::flex();
        for (stem, channels) in [(1, vec![4, 8, 8]), (2, vec![4, 8])] {
            let config = DiscriminatorConfig::new()
                .with_height(8)
                .with_width(64)
                .with_stem(stem)
                .with_channels(channels)
                .with_seed(3);
            let whole = config.init(&dev);
            let fresh = config
                .clone()
                .with_width(16)
                .with_azimuth_input(true)
                .with_seed(9)
                .init(&dev);
            let windows = whole.clone().into_windows(fresh, 2);
            let tile = Rng::new(5).normal_tensor([4, 1, 8, 16], &dev);
            let turn = Tensor::cat(vec![tile.clone(); 4], 3);
            let expected = tensor_to_vec(whole.forward(turn));
            let azimuth = column_azimuths(&[16, 48, 0, 7], 16, 64, &dev);
            let got = tensor_to_vec(windows.forward_at(tile, Some(azimuth)));
            for (g, e) in got.iter().zip(&expected) {
                assert!(
                    (g - e).abs() < 1e-3 * (1.0 + e.abs()),
                    "stem {stem}: {got:?} vs {expected:?}"
                );
            }
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
