//! The segmentation network: a light U-Net on range images. Every 3x3 convolution pads
//! circularly along azimuth when the input is a whole revolution (a scan has no left or right
//! edge) and with zeros otherwise (training crops) and along elevation; batch norm and ReLU
//! after each; 2x2 max pooling down, nearest-neighbour upsampling and skip connections up;
//! a 1x1 head gives one logit per class and pixel.

use burn::config::Config;
use burn::module::Module;
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::pool::{MaxPool2d, MaxPool2dConfig};
use burn::nn::{BatchNorm, BatchNormConfig, PaddingConfig2d};
use burn::tensor::activation::relu;
use burn::tensor::{Device, Tensor};

use super::classes::NUM_CLASSES;
use super::data::CHANNELS;
use crate::util::init::conv2d as seeded;
use crate::util::rng::Rng;
use crate::util::tensor::upsample_nearest;

#[derive(Config, Debug)]
pub struct SegNetConfig {
    /// Channels of the encoder levels; each level halves both image axes.
    #[config(default = "vec![16, 32, 48, 64]")]
    pub widths: Vec<usize>,
    #[config(default = "CHANNELS")]
    pub d_input: usize,
    #[config(default = "NUM_CLASSES")]
    pub classes: usize,
}

impl SegNetConfig {
    /// Refuses sizes this version cannot build or that would not fit in memory.
    pub fn check(&self) -> anyhow::Result<()> {
        use crate::util::bounds;
        bounds::sizes("net.widths", &self.widths, 1..=8, 1..=1024)?;
        bounds::size("net.d_input", self.d_input, CHANNELS..=CHANNELS)?;
        bounds::size("net.classes", self.classes, NUM_CLASSES..=NUM_CLASSES)
    }

    /// Both image axes must divide by this.
    pub fn multiple(&self) -> usize {
        1 << self.widths.len().saturating_sub(1)
    }

    /// A fresh network, its weights drawn from `rng` (so a run repeats exactly).
    pub fn init(&self, rng: &mut Rng, device: &Device) -> SegNet {
        let w = &self.widths;
        let mut encoder = Vec::new();
        let mut d_in = self.d_input;
        for &d in w {
            encoder.push(Block::new(d_in, d, rng, device));
            d_in = d;
        }
        // Level i of the decoder takes the upsampled level below and the encoder's skip.
        let mut decoder = Vec::new();
        for i in (0..w.len() - 1).rev() {
            let d_out = w[i.saturating_sub(1)];
            decoder.push(Block::new(d_in + w[i], d_out, rng, device));
            d_in = d_out;
        }
        SegNet {
            encoder,
            decoder,
            pool: MaxPool2dConfig::new([2, 2]).init(),
            head: seeded(Conv2dConfig::new([d_in, self.classes], [1, 1]), rng, device),
        }
    }
}

/// 3x3 convolution, batch norm, ReLU.
#[derive(Module, Debug)]
pub struct ConvBn {
    conv: Conv2d,
    norm: BatchNorm,
}

impl ConvBn {
    fn new(d_in: usize, d_out: usize, rng: &mut Rng, device: &Device) -> Self {
        ConvBn {
            conv: seeded(
                Conv2dConfig::new([d_in, d_out], [3, 3])
                    .with_padding(PaddingConfig2d::Valid)
                    .with_bias(false),
                rng,
                device,
            ),
            norm: BatchNormConfig::new(d_out).init(device),
        }
    }

    fn forward(&self, x: Tensor<4>, circular: bool) -> Tensor<4> {
        relu(self.norm.forward(self.conv.forward(pad1(x, circular))))
    }
}

/// Two [`ConvBn`].
#[derive(Module, Debug)]
pub struct Block {
    a: ConvBn,
    b: ConvBn,
}

impl Block {
    fn new(d_in: usize, d_out: usize, rng: &mut Rng, device: &Device) -> Self {
        Block {
            a: ConvBn::new(d_in, d_out, rng, device),
            b: ConvBn::new(d_out, d_out, rng, device),
        }
    }

    fn forward(&self, x: Tensor<4>, circular: bool) -> Tensor<4> {
        self.b.forward(self.a.forward(x, circular), circular)
    }
}

#[derive(Module, Debug)]
pub struct SegNet {
    encoder: Vec<Block>,
    decoder: Vec<Block>,
    pool: MaxPool2d,
    head: Conv2d,
}

impl SegNet {
    /// Class logits.
    ///
    /// # Shapes
    /// - x: `[batch, CHANNELS, H, W]` -> `[batch, classes, H, W]`; H and W divisible by
    ///   [`SegNetConfig::multiple`].
    pub fn forward(&self, x: Tensor<4>, circular: bool) -> Tensor<4> {
        let mut skips = Vec::with_capacity(self.encoder.len());
        let mut h = x;
        for (i, block) in self.encoder.iter().enumerate() {
            if i > 0 {
                h = self.pool.forward(h);
            }
            h = block.forward(h, circular);
            skips.push(h.clone());
        }
        skips.pop();
        for block in &self.decoder {
            let skip = skips.pop().expect("one skip per decoder level");
            h = block.forward(Tensor::cat(vec![upsample_nearest(h), skip], 1), circular);
        }
        self.head.forward(h)
    }
}

/// Pad one pixel on every side: circular or zero along W, zero along H.
fn pad1(x: Tensor<4>, circular: bool) -> Tensor<4> {
    let [b, c, h, w] = x.dims();
    let device = x.device();
    let (left, right) = if circular {
        (x.clone().narrow(3, w - 1, 1), x.clone().narrow(3, 0, 1))
    } else {
        let z = Tensor::zeros([b, c, h, 1], &device);
        (z.clone(), z)
    };
    let x = Tensor::cat(vec![left, x, right], 3);
    let z = Tensor::zeros([b, c, 1, w + 2], &device);
    Tensor::cat(vec![z.clone(), x, z], 2)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::util::tensor::tensor_to_vec;

    #[test]
    fn logits_have_the_input_grid_and_whole_scans_are_shift_equivariant() {
        let device = Device::flex();
        let mut rng = Rng::new(1);
        let net = SegNetConfig::new().init(&mut rng, &device);
        let (h, w) = (8, 32);
        let x = rng.normal_tensor([1, CHANNELS, h, w], &device);
        let y = net.forward(x.clone(), true);
        assert_eq!(y.dims(), [1, NUM_CLASSES, h, w]);
        // Rolling a whole revolution by the pooling stride rolls the logits with it.
        let s = 8;
        let roll = |t: Tensor<4>| {
            let w = t.dims()[3];
            Tensor::cat(
                vec![t.clone().narrow(3, w - s, s), t.narrow(3, 0, w - s)],
                3,
            )
        };
        let a = tensor_to_vec(roll(y));
        let b = tensor_to_vec(net.forward(roll(x), true));
        let err = a
            .iter()
            .zip(&b)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f32::max);
        assert!(err < 1e-4, "max difference {err}");
    }

    #[test]
    fn the_seed_alone_decides_the_initial_weights() {
        let device = Device::flex();
        let x = Rng::new(9).normal_tensor([1, CHANNELS, 8, 16], &device);
        let logits = |seed| {
            let net = SegNetConfig::new().init(&mut Rng::new(seed), &device);
            tensor_to_vec(net.forward(x.clone(), false))
        };
        assert_eq!(logits(3), logits(3));
        assert_ne!(logits(3), logits(4));
    }
}
