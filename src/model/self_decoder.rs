//! The discriminator's self-supervised decoder (FastGAN, Liu et al. 2021): a small
//! convolutional decoder that rebuilds a real scan, at half its resolution, from the
//! discriminator's last feature map. Trained beside the discriminator on the scans it is
//! shown as real, it makes those features describe the whole scan (its layout, objects and
//! drops) rather than only the few cues that separate the training scans from generated
//! ones, which is how a discriminator learns some 600 scans by heart. It needs no
//! pretrained weights and is used in training only.

use burn::config::Config;
use burn::module::Module;
use burn::tensor::{Device, Tensor};

use super::conv::{EqualConv, EqualConvConfig, downsample2x};
use crate::util::rng::Rng;
use crate::util::tensor::upsample_nearest;

#[derive(Config, Debug)]
pub struct SelfDecoderConfig {
    /// Channels of the discriminator's last feature map.
    pub d_input: usize,
    /// How many times the feature map is upsampled 2x: the discriminator's fold (input
    /// pixels per feature pixel, per side) over 2, in powers of two.
    pub ups: usize,
    #[config(default = 7)]
    pub seed: u64,
}

#[derive(Module, Debug)]
pub struct SelfDecoder {
    /// A 1x1 projection to the first upsampling's width.
    pub from_features: EqualConv,
    /// One 3x3 convolution after each nearest-neighbour 2x upsampling.
    pub ups: Vec<EqualConv>,
    /// The rebuilt scan (network units), one channel.
    pub to_image: EqualConv,
}

impl SelfDecoderConfig {
    /// The decoder of a discriminator whose last feature map has `channels` and whose
    /// input is `fold` times larger per side.
    pub fn for_discriminator(channels: usize, fold: usize) -> Self {
        Self::new(channels, fold.max(2).ilog2() as usize - 1)
    }

    /// Widths: a quarter of the features' (at least 8), halved at each upsampling.
    fn widths(&self) -> Vec<usize> {
        let first = (self.d_input / 4).max(8);
        (0..=self.ups).map(|i| (first >> i).max(8)).collect()
    }

    pub fn init(&self, device: &Device) -> SelfDecoder {
        let mut rng = Rng::new(self.seed);
        let c = self.widths();
        SelfDecoder {
            from_features: EqualConvConfig::new(self.d_input, c[0])
                .with_kernel(1)
                .init(&mut rng, device),
            ups: (0..self.ups)
                .map(|i| EqualConvConfig::new(c[i], c[i + 1]).init(&mut rng, device))
                .collect(),
            to_image: EqualConvConfig::new(c[self.ups], 1)
                .with_kernel(1)
                .with_activate(false)
                .init(&mut rng, device),
        }
    }
}

impl SelfDecoder {
    /// # Shapes
    /// - features: `[batch, ch, h, w]` -> `[batch, 1, h * 2^ups, w * 2^ups]`
    pub fn forward(&self, features: Tensor<4>) -> Tensor<4> {
        let mut y = self.from_features.forward(features);
        for conv in &self.ups {
            y = conv.forward(upsample_nearest(y));
        }
        self.to_image.forward(y)
    }

    /// The reconstruction loss of one batch: mean squared error between the decoder's
    /// output from `features` and `input` (what the discriminator saw) downsampled 2x.
    ///
    /// # Shapes
    /// - features: `[batch, ch, h, w]`, input: `[batch, 1, H, W]` -> scalar
    pub fn loss(&self, features: Tensor<4>, input: Tensor<4>) -> Tensor<1> {
        let target = downsample2x(input.detach());
        (self.forward(features) - target).powi_scalar(2).mean()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::discriminator::DiscriminatorConfig;

    #[test]
    fn the_decoder_rebuilds_the_discriminators_input_at_half_resolution() {
        let dev = Device::flex();
        for (stem, channels) in [(1, vec![4, 8, 8, 16]), (2, vec![4, 8, 16])] {
            let config = DiscriminatorConfig::new()
                .with_height(16)
                .with_width(64)
                .with_stem(stem)
                .with_channels(channels.clone());
            let d = config.init(&dev);
            let fold = stem << (channels.len() - 1);
            let decoder = SelfDecoderConfig::for_discriminator(16, fold).init(&dev);
            let x = Rng::new(3).normal_tensor([2, 1, 16, 64], &dev);
            let features = d.features_at(x.clone(), None);
            assert_eq!(features.dims(), [2, 16, 2, 8]);
            assert_eq!(decoder.forward(features.clone()).dims(), [2, 1, 8, 32]);
            assert!(decoder.loss(features, x).into_scalar::<f32>() > 0.0);
        }
    }

    #[test]
    fn the_reconstruction_trains_the_discriminator_too() {
        let dev = Device::flex().autodiff();
        let d = DiscriminatorConfig::new()
            .with_height(8)
            .with_width(32)
            .with_channels(vec![4, 8, 8])
            .init(&dev);
        let decoder = SelfDecoderConfig::for_discriminator(8, 4).init(&dev);
        let x = Rng::new(1).normal_tensor([2, 1, 8, 32], &dev);
        let grads = decoder.loss(d.features_at(x.clone(), None), x).backward();
        assert!(d.blocks[0].conv0.weight.val().grad(&grads).is_some());
        assert!(decoder.ups[0].weight.val().grad(&grads).is_some());
        // The head is not on the reconstruction's path.
        assert!(d.fc.weight.val().grad(&grads).is_none());
    }
}
