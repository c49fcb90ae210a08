//! The encoder of the spatial-latent model: a small convolutional U-Net from an observed range
//! image (on the sensor's own grid) to the latent grid at half its resolution in both axes.
//!
//! Every 3x3 convolution pads circularly along azimuth when the input is a whole turn (a scan
//! has no left or right edge) and with zeros otherwise (training crops), and with zeros along
//! elevation. The deepest level (1/8) widens its view along azimuth with dilated convolutions,
//! so a hole of tens of degrees still sees surfaces on both of its sides.

use burn::config::Config;
use burn::module::Module;
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::tensor::activation::leaky_relu;
use burn::tensor::{Device, Tensor};

use crate::util::init::conv2d;
use crate::util::rng::Rng;
use crate::util::tensor::upsample_nearest;

/// Input channels of the encoder: what is known of each ray and its prior (9), and its angles
/// (3); see [`super::encoder_input`].
pub const INPUT_CHANNELS: usize = 12;

/// Both image axes of the encoder's input must divide by this.
pub const MULTIPLE: usize = 8;

pub(super) const SLOPE: f64 = 0.2;

#[derive(Config, Debug, PartialEq)]
pub struct EncoderConfig {
    /// Channels at 1/2, 1/4 and 1/8 of the input resolution.
    #[config(default = "[24, 40, 56]")]
    pub widths: [usize; 3],
    /// Azimuth dilations of the residual convolutions at 1/8.
    #[config(default = "vec![1, 2, 4, 8]")]
    pub dilations: Vec<usize>,
    /// Channels of the latent grid (1/2 resolution).
    #[config(default = 32)]
    pub latent: usize,
}

/// A 3x3 convolution with its azimuth dilation, padded by hand (circular or zero).
#[derive(Module, Debug)]
pub struct Conv3 {
    pub(super) conv: Conv2d,
    pub(super) dilation: usize,
}

impl Conv3 {
    fn new(d_in: usize, d_out: usize, dilation: usize, rng: &mut Rng, device: &Device) -> Self {
        let config = Conv2dConfig::new([d_in, d_out], [3, 3]).with_dilation([1, dilation]);
        Conv3 {
            conv: conv2d(config, rng, device),
            dilation,
        }
    }

    fn forward(&self, x: Tensor<4>, circular: bool) -> Tensor<4> {
        self.conv.forward(pad(x, 1, self.dilation, circular))
    }
}

#[derive(Module, Debug)]
pub struct Encoder {
    /// 2x2 stride-2 patch embedding to 1/2 resolution.
    pub(super) stem: Conv2d,
    pub(super) half: Vec<Conv3>,
    pub(super) down_quarter: Conv3,
    pub(super) quarter: Conv3,
    pub(super) down_eighth: Conv3,
    pub(super) eighth: Vec<Conv3>,
    pub(super) up_quarter: Conv3,
    pub(super) up_half: Conv3,
    pub(super) out: Conv2d,
}

impl EncoderConfig {
    pub fn init(&self, rng: &mut Rng, device: &Device) -> Encoder {
        let [c0, c1, c2] = self.widths;
        Encoder {
            stem: conv2d(
                Conv2dConfig::new([INPUT_CHANNELS, c0], [2, 2]).with_stride([2, 2]),
                rng,
                device,
            ),
            half: vec![
                Conv3::new(c0, c0, 1, rng, device),
                Conv3::new(c0, c0, 1, rng, device),
            ],
            down_quarter: Conv3::new(c0, c1, 1, rng, device),
            quarter: Conv3::new(c1, c1, 1, rng, device),
            down_eighth: Conv3::new(c1, c2, 1, rng, device),
            eighth: self
                .dilations
                .iter()
                .map(|&d| Conv3::new(c2, c2, d, rng, device))
                .collect(),
            up_quarter: Conv3::new(c2 + c1, c1, 1, rng, device),
            up_half: Conv3::new(c1 + c0, c0, 1, rng, device),
            out: conv2d(Conv2dConfig::new([c0, self.latent], [1, 1]), rng, device),
        }
    }
}

impl Encoder {
    /// The latent grid of an observation.
    ///
    /// # Shapes
    /// - x: `[batch, INPUT_CHANNELS, H, W]`, H and W divisible by [`MULTIPLE`]
    /// - returns `[batch, latent, H / 2, W / 2]`
    pub fn forward(&self, x: Tensor<4>, circular: bool) -> Tensor<4> {
        let act = |t: Tensor<4>| leaky_relu(t, SLOPE);
        let mut h = act(self.stem.forward(x));
        for conv in &self.half {
            h = h.clone() + act(conv.forward(h, circular));
        }
        let half = h;
        let q = act(self.down_quarter.forward(pool2(half.clone()), circular));
        let quarter = q.clone() + act(self.quarter.forward(q, circular));
        let mut e = act(self.down_eighth.forward(pool2(quarter.clone()), circular));
        for conv in &self.eighth {
            e = e.clone() + act(conv.forward(e, circular));
        }
        let q = act(self
            .up_quarter
            .forward(Tensor::cat(vec![upsample_nearest(e), quarter], 1), circular));
        let h = act(self
            .up_half
            .forward(Tensor::cat(vec![upsample_nearest(q), half], 1), circular));
        self.out.forward(h)
    }
}

/// 2x2 average pooling.
fn pool2(x: Tensor<4>) -> Tensor<4> {
    let [b, c, h, w] = x.dims();
    x.reshape([b, c, h / 2, 2, w / 2, 2])
        .mean_dim(5)
        .mean_dim(3)
        .reshape([b, c, h / 2, w / 2])
}

/// Pads `ph` rows of zeros above and below, and `pw` columns on each side: the other end of
/// the turn when `circular`, zeros otherwise.
pub fn pad(x: Tensor<4>, ph: usize, pw: usize, circular: bool) -> Tensor<4> {
    let [b, c, h, w] = x.dims();
    let device = x.device();
    let x = if pw == 0 {
        x
    } else if circular && pw <= w {
        let left = x.clone().narrow(3, w - pw, pw);
        let right = x.clone().narrow(3, 0, pw);
        Tensor::cat(vec![left, x, right], 3)
    } else {
        let z = Tensor::zeros([b, c, h, pw], &device);
        Tensor::cat(vec![z.clone(), x, z], 3)
    };
    if ph == 0 {
        return x;
    }
    let z = Tensor::zeros([b, c, ph, w + 2 * pw], &device);
    Tensor::cat(vec![z.clone(), x, z], 2)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::util::tensor::tensor_to_vec;

    #[test]
    fn the_latent_is_half_the_grid_and_whole_turns_are_shift_equivariant() {
        let device = Device::flex();
        let mut rng = Rng::new(2);
        let enc = EncoderConfig::new().init(&mut rng, &device);
        let (h, w) = (16, 64);
        let x = rng.normal_tensor([1, INPUT_CHANNELS, h, w], &device);
        let y = enc.forward(x.clone(), true);
        assert_eq!(y.dims(), [1, 32, h / 2, w / 2]);
        // Rolling the input by 16 columns rolls the latent by 8 cells.
        let rolled = Tensor::cat(vec![x.clone().narrow(3, 16, w - 16), x.narrow(3, 0, 16)], 3);
        let y2 = tensor_to_vec(enc.forward(rolled, true));
        let y = tensor_to_vec(y);
        let (hl, wl) = (h / 2, w / 2);
        for c in 0..32 {
            for i in 0..hl {
                for j in 0..wl {
                    let a = y[(c * hl + i) * wl + (j + 8) % wl];
                    let b = y2[(c * hl + i) * wl + j];
                    assert!((a - b).abs() < 1e-4, "c{c} i{i} j{j}: {a} vs {b}");
                }
            }
        }
    }
}
