//! Seeded initialisation of burn's layers: weights drawn from our own [`Rng`] rather than the
//! backend's unseeded generator, so a training run repeats exactly from its seed.

use burn::module::Param;
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::{Initializer, Linear, LinearConfig};
use burn::tensor::Device;

use super::rng::Rng;
use super::tensor::tensor_from;

/// `n` values uniform within +-`bound`.
fn uniform(rng: &mut Rng, n: usize, bound: f32) -> Vec<f32> {
    rng.uniform_vec(n)
        .into_iter()
        .map(|u| (2.0 * u - 1.0) * bound)
        .collect()
}

/// A convolution with burn's default initialisation (weights and bias uniform within
/// +-1/sqrt(fan_in)), drawn from `rng`.
pub fn conv2d(config: Conv2dConfig, rng: &mut Rng, device: &Device) -> Conv2d {
    let [d_in, d_out] = config.channels;
    let [kh, kw] = config.kernel_size;
    let bound = 1.0 / ((d_in * kh * kw) as f32).sqrt();
    let weight = tensor_from(
        uniform(rng, d_out * d_in * kh * kw, bound),
        [d_out, d_in, kh, kw],
        device,
    );
    let bias = config
        .bias
        .then(|| Param::from_tensor(tensor_from(uniform(rng, d_out, bound), [d_out], device)));
    // Zeros: nothing is drawn from the backend's generator; both are replaced.
    let mut conv = config.with_initializer(Initializer::Zeros).init(device);
    conv.weight = Param::from_tensor(weight);
    conv.bias = bias;
    conv
}

/// A linear layer initialised like [`conv2d`], drawn from `rng`.
pub fn linear(config: LinearConfig, rng: &mut Rng, device: &Device) -> Linear {
    let (d_in, d_out) = (config.d_input, config.d_output);
    let bound = 1.0 / (d_in as f32).sqrt();
    let weight = tensor_from(uniform(rng, d_in * d_out, bound), [d_in, d_out], device);
    let bias = config
        .bias
        .then(|| Param::from_tensor(tensor_from(uniform(rng, d_out, bound), [d_out], device)));
    let mut layer = config.with_initializer(Initializer::Zeros).init(device);
    layer.weight = Param::from_tensor(weight);
    layer.bias = bias;
    layer
}
