//! The paper's fixed-resolution baselines: a DCGAN-style transposed-convolution generator that
//! maps z straight to a range image. With two output channels (inverse depth + keep logit) and
//! the measurement model it is DUSty v1; with one channel (the raw image, dropped pixels = -1)
//! it is the "vanilla" GAN. Neither can change its output resolution.

use burn::config::Config;
use burn::module::{Module, Param};
use burn::tensor::module::conv_transpose2d;
use burn::tensor::ops::ConvTransposeOptions;
use burn::tensor::{Device, Tensor};

use super::conv::{EqualConv, EqualConvConfig};
use super::layers::{EqualLinear, EqualLinearConfig};
use crate::util::rng::Rng;

#[derive(Config, Debug)]
pub struct ConvGeneratorConfig {
    #[config(default = 512)]
    pub d_z: usize,
    /// Channels at 4x32, then after each x2 transposed conv.
    #[config(default = "vec![512, 256, 128, 64, 32]")]
    pub channels: Vec<usize>,
    #[config(default = 4)]
    pub base_height: usize,
    #[config(default = 32)]
    pub base_width: usize,
    /// 2 = DUSty v1 (inverse depth + keep logit), 1 = vanilla (raw image).
    #[config(default = 2)]
    pub out_channels: usize,
    #[config(default = 0)]
    pub seed: u64,
}

impl ConvGeneratorConfig {
    /// Refuses sizes that cannot be built or would not fit in memory.
    pub fn check(&self) -> anyhow::Result<()> {
        use crate::util::bounds;
        bounds::sizes("conv_generator.channels", &self.channels, 1..=8, 1..=4096)?;
        bounds::size("conv_generator.d_z", self.d_z, 1..=4096)?;
        bounds::size("conv_generator.base_height", self.base_height, 1..=64)?;
        bounds::size("conv_generator.base_width", self.base_width, 1..=512)?;
        bounds::size("conv_generator.out_channels", self.out_channels, 1..=2)
    }
}

/// Transposed conv 4x4, stride 2 (equalised lr) + LeakyReLU.
#[derive(Module, Debug)]
pub struct UpConv {
    /// `[in, out, 4, 4]`
    pub weight: Param<Tensor<4>>,
    pub bias: Param<Tensor<1>>,
    #[module(skip)]
    pub weight_gain: f32,
}

impl UpConv {
    fn new(d_in: usize, d_out: usize, rng: &mut Rng, device: &Device) -> Self {
        Self {
            weight: Param::from_tensor(rng.normal_tensor([d_in, d_out, 4, 4], device)),
            bias: Param::from_tensor(Tensor::zeros([d_out], device)),
            // each output pixel sees d_in * 2 * 2 taps of the stride-2 kernel
            weight_gain: 1.0 / ((d_in * 4) as f32).sqrt(),
        }
    }

    /// # Shapes
    /// - x: `[batch, in, H, W]` -> `[batch, out, 2H, 2W]`
    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let y = conv_transpose2d(
            x,
            self.weight.val().mul_scalar(self.weight_gain),
            Some(self.bias.val()),
            ConvTransposeOptions::new([2, 2], [1, 1], [0, 0], [1, 1], 1),
        );
        super::layers::lrelu_gain(y)
    }
}

#[derive(Module, Debug)]
pub struct ConvGenerator {
    pub fc: EqualLinear,
    pub ups: Vec<UpConv>,
    pub to_out: EqualConv,
    #[module(skip)]
    pub base: [usize; 3],
}

impl ConvGeneratorConfig {
    /// Same widths as the chosen CPU DUSty v2 generator (docs/model_benchmarks.md).
    pub fn cpu(out_channels: usize) -> Self {
        Self::new()
            .with_d_z(128)
            .with_channels(vec![128, 64, 32, 16, 16])
            .with_out_channels(out_channels)
    }

    /// The size of the images it renders (`ConvGenerator::resolution`).
    pub fn output_size(&self) -> (usize, usize) {
        let k = 1 << self.channels.len().saturating_sub(1);
        (self.base_height * k, self.base_width * k)
    }

    pub fn init(&self, device: &Device) -> ConvGenerator {
        let mut rng = Rng::new(self.seed);
        let c = &self.channels;
        let fc = EqualLinearConfig::new(self.d_z, c[0] * self.base_height * self.base_width)
            .with_activate(true)
            .init(&mut rng, device);
        let ups = (1..c.len())
            .map(|i| UpConv::new(c[i - 1], c[i], &mut rng, device))
            .collect();
        let to_out = EqualConvConfig::new(c[c.len() - 1], self.out_channels)
            .with_kernel(1)
            .with_activate(false)
            .init(&mut rng, device);
        ConvGenerator {
            fc,
            ups,
            to_out,
            base: [c[0], self.base_height, self.base_width],
        }
    }
}

impl ConvGenerator {
    pub fn d_z(&self) -> usize {
        self.fc.weight.dims()[1]
    }

    /// Output size.
    pub fn resolution(&self) -> (usize, usize) {
        let k = 1 << self.ups.len();
        (self.base[1] * k, self.base[2] * k)
    }

    /// # Shapes
    /// - z: `[batch, d_z]` -> `[batch, out_channels, H, W]` (channel 0 through tanh)
    pub fn forward(&self, z: Tensor<2>) -> Tensor<4> {
        let b = z.dims()[0];
        let [c, h, w] = self.base;
        let norm = z.clone().powi_scalar(2).mean_dim(1).add_scalar(1e-8).sqrt(); // [batch, 1]
        let mut x = self.fc.forward(z / norm).reshape([b, c, h, w]); // [batch, c0, 4, 32]
        for up in &self.ups {
            x = up.forward(x); // [batch, c, 2h, 2w]
        }
        let y = self.to_out.forward(x); // [batch, out, H, W]
        let n_out = y.dims()[1];
        let x_d = y.clone().narrow(1, 0, 1).tanh(); // [batch, 1, H, W]
        if n_out > 1 {
            Tensor::cat(vec![x_d, y.narrow(1, 1, n_out - 1)], 1)
        } else {
            x_d
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn conv_generator_shapes_and_gradients() {
        let dev = Device::flex().autodiff();
        let g = ConvGeneratorConfig::new()
            .with_d_z(8)
            .with_channels(vec![8, 4, 4])
            .init(&dev);
        assert_eq!(g.resolution(), (16, 128));
        let z = Rng::new(1).normal_tensor([2, 8], &dev);
        let y = g.forward(z);
        assert_eq!(y.dims(), [2, 2, 16, 128]);
        let grads = y.sum().backward();
        assert!(g.fc.weight.val().grad(&grads).is_some());
        assert!(g.ups[0].weight.val().grad(&grads).is_some());
    }
}
