//! The fast path: an amortised encoder that predicts the latent w of an observed range image in
//! one forward pass, so only a few refinement steps are left to the optimiser.
//!
//! A small strided CNN (circular padding along azimuth, replicate along elevation) from the
//! observed inverse depth and its validity mask to w - w_avg. Trained against the frozen
//! generator by [`crate::train::encoder`]; the shipped weights are compiled in from
//! `models/encoder/`.

use std::path::Path;

use anyhow::{Context, Result};
use burn::config::Config;
use burn::module::{Module, Param};
use burn::store::ModuleRecord;
use burn::tensor::activation::leaky_relu;
use burn::tensor::module::conv2d;
use burn::tensor::ops::ConvOptions;
use burn::tensor::{Bytes, Device, Tensor};

use crate::model::conv::pad_circular;
use crate::model::layers::{EqualLinear, EqualLinearConfig};
use crate::util::rng::Rng;

/// The shipped encoder's configuration and weights (trained against `models/dusty2`).
const SHIPPED_CONFIG: &str = include_str!("../../models/encoder/config.json");
const SHIPPED_WEIGHTS: &[u8] = include_bytes!("../../models/encoder/encoder.bpk");

/// 3x3 convolution with circular-W / replicate-H padding and a stride, equalised learning rate.
#[derive(Config, Debug)]
pub struct StridedConvConfig {
    pub d_input: usize,
    pub d_output: usize,
    /// Stride along (H, W).
    pub stride: [usize; 2],
}

#[derive(Module, Debug)]
pub struct StridedConv {
    /// `[out, in, 3, 3]`
    pub weight: Param<Tensor<4>>,
    pub bias: Param<Tensor<1>>,
    #[module(skip)]
    pub stride: [usize; 2],
    #[module(skip)]
    pub gain: f32,
}

impl StridedConvConfig {
    pub fn init(&self, rng: &mut Rng, device: &Device) -> StridedConv {
        StridedConv {
            weight: Param::from_tensor(
                rng.normal_tensor([self.d_output, self.d_input, 3, 3], device),
            ),
            bias: Param::from_tensor(Tensor::zeros([self.d_output], device)),
            stride: self.stride,
            gain: 1.0 / ((self.d_input * 9) as f32).sqrt(),
        }
    }
}

impl StridedConv {
    /// # Shapes
    /// - x: `[batch, in, H, W]` -> `[batch, out, H / s_h, W / s_w]`
    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let x = pad_circular(x, 1); // [batch, in, H + 2, W + 2]
        let y = conv2d(
            x,
            self.weight.val().mul_scalar(self.gain),
            Some(self.bias.val()),
            ConvOptions::new(self.stride, [0, 0], [1, 1], 1),
        );
        leaky_relu(y, 0.2).mul_scalar(std::f32::consts::SQRT_2)
    }
}

/// Encoder from a 64 x 512 observation to w. Five stride-2 convolutions (64x512 -> 2x16), one
/// stride-(1, 2) convolution (-> 2x8), then two equalised linear layers to `d_w`.
#[derive(Config, Debug)]
pub struct EncoderConfig {
    /// Input grid (the model grid).
    #[config(default = 64)]
    pub height: usize,
    #[config(default = 512)]
    pub width: usize,
    /// Output channels of the convolutions.
    #[config(default = "vec![16, 32, 48, 64, 64, 64]")]
    pub channels: Vec<usize>,
    #[config(default = 128)]
    pub d_hidden: usize,
    /// Latent size of the generator it serves.
    #[config(default = 128)]
    pub d_w: usize,
    #[config(default = 11)]
    pub seed: u64,
}

#[derive(Module, Debug)]
pub struct Encoder {
    pub convs: Vec<StridedConv>,
    pub fc: EqualLinear,
    pub out: EqualLinear,
}

impl EncoderConfig {
    /// Refuses sizes that cannot be built or would not fit in memory.
    pub fn check(&self) -> Result<()> {
        use crate::util::bounds;
        bounds::size("encoder.height", self.height, 1..=4096)?;
        bounds::size("encoder.width", self.width, 1..=16384)?;
        bounds::sizes("encoder.channels", &self.channels, 1..=8, 1..=1024)?;
        bounds::size("encoder.d_hidden", self.d_hidden, 1..=8192)?;
        bounds::size("encoder.d_w", self.d_w, 1..=4096)
    }

    /// Spatial size after the convolutions.
    fn feature_dims(&self) -> (usize, usize) {
        let n = self.channels.len();
        let h = self.height >> n.min(5);
        let w = self.width >> n;
        (h.max(1), w.max(1))
    }

    fn strides(&self) -> Vec<[usize; 2]> {
        (0..self.channels.len())
            .map(|i| if i < 5 { [2, 2] } else { [1, 2] })
            .collect()
    }

    pub fn init(&self, device: &Device) -> Encoder {
        let mut rng = Rng::new(self.seed);
        let mut d_in = 2;
        let mut convs = Vec::new();
        for (c, stride) in self.channels.iter().zip(self.strides()) {
            convs.push(StridedConvConfig::new(d_in, *c, stride).init(&mut rng, device));
            d_in = *c;
        }
        let (h, w) = self.feature_dims();
        Encoder {
            convs,
            fc: EqualLinearConfig::new(d_in * h * w, self.d_hidden)
                .with_activate(true)
                .init(&mut rng, device),
            out: EqualLinearConfig::new(self.d_hidden, self.d_w).init(&mut rng, device),
        }
    }
}

impl Encoder {
    /// Predict w - w_avg.
    ///
    /// # Shapes
    /// - target_net: `[batch, 1, H, W]` network units (no return = -1), mask `[batch, 1, H, W]`
    /// - -> `[batch, d_w]`
    pub fn forward(&self, target_net: Tensor<4>, mask: Tensor<4>) -> Tensor<2> {
        let b = target_net.dims()[0];
        let x_d = target_net.add_scalar(1.0).mul_scalar(0.5) * mask.clone(); // [batch, 1, H, W]
        let mut x = Tensor::cat(
            vec![x_d.mul_scalar(2.0), mask.mul_scalar(2.0).sub_scalar(1.0)],
            1,
        ); // [batch, 2, H, W]
        for conv in &self.convs {
            x = conv.forward(x); // [batch, ch, H / 2^k, W / 2^k]
        }
        let x = x.reshape([b as i32, -1]); // [batch, ch * h * w]
        let x = self.fc.forward(x); // [batch, d_hidden]
        self.out.forward(x) // [batch, d_w]
    }
}

/// A trained encoder with its configuration.
#[derive(Debug, Clone)]
pub struct TrainedEncoder {
    pub encoder: Encoder,
    pub config: EncoderConfig,
    /// "shipped" or the directory it came from.
    pub source: String,
}

impl TrainedEncoder {
    /// The weights shipped in `models/encoder`, compiled into the binary.
    pub fn shipped(device: &Device) -> Result<Self> {
        let config: EncoderConfig =
            serde_json::from_str(SHIPPED_CONFIG).context("the shipped encoder's config.json")?;
        let record = ModuleRecord::from_bytes(Bytes::from_bytes_vec(SHIPPED_WEIGHTS.to_vec()))
            .map_err(|e| anyhow::anyhow!("the shipped encoder weights are unreadable: {e}"))?;
        let encoder = config
            .init(device)
            .try_load_record(record)
            .map_err(|e| anyhow::anyhow!("the shipped encoder weights do not fit: {e}"))?;
        Ok(Self {
            encoder,
            config,
            source: "shipped".into(),
        })
    }

    /// A model directory (`config.json` = [`EncoderConfig`], `encoder.bpk`) or an encoder run directory
    /// (`config.json` with an `encoder` entry, `checkpoint/encoder.bpk`).
    pub fn from_dir(dir: &Path, device: &Device) -> Result<Self> {
        let direct = dir.join("encoder.bpk");
        let config_path = dir.join("config.json");
        let text = std::fs::read_to_string(&config_path)
            .with_context(|| format!("failed to read '{}'", config_path.display()))?;
        let saved: serde_json::Value = serde_json::from_str(&text)
            .with_context(|| format!("bad config '{}'", config_path.display()))?;
        // A training run keeps the encoder's shape under `encoder`, beside its settings.
        let (saved, weights) = if direct.is_file() {
            (saved, direct)
        } else {
            let entry = saved.get("encoder").cloned().unwrap_or_default();
            (entry, dir.join("checkpoint").join("encoder.bpk"))
        };
        let config: EncoderConfig = serde_json::from_value(saved)
            .with_context(|| format!("bad encoder config in '{}'", config_path.display()))?;
        config.check().with_context(|| {
            format!("{}: bad encoder config", dir.join("config.json").display())
        })?;
        let encoder = config
            .init(device)
            .try_load_file(&weights)
            .map_err(|e| anyhow::anyhow!("failed to load '{}': {e}", weights.display()))?;
        Ok(Self {
            encoder,
            config,
            source: dir.display().to_string(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn encoder_maps_a_scan_to_one_latent_and_is_circular() {
        let dev = Device::flex();
        let cfg = EncoderConfig::new()
            .with_height(16)
            .with_width(64)
            .with_channels(vec![4, 4, 4])
            .with_d_hidden(8)
            .with_d_w(6);
        let enc = cfg.init(&dev);
        let mut rng = Rng::new(1);
        let x = rng.normal_tensor([2, 1, 16, 64], &dev).clamp(-1.0, 1.0);
        let m = x.clone().greater_elem(-0.5).float();
        let w = enc.forward(x, m);
        assert_eq!(w.dims(), [2, 6]);
    }

    #[test]
    fn shipped_encoder_loads() {
        let dev = Device::flex();
        let e = TrainedEncoder::shipped(&dev).expect("shipped encoder");
        assert_eq!((e.config.height, e.config.width), (64, 512));
    }
}
