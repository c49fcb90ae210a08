//! The lossy measurement (ray-drop) model: turns the generator's inverse depth and keep logit
//! into a measured range image through a Bernoulli mask, reparameterised with the
//! straight-through Gumbel-sigmoid so the generator gets gradients through the sampling.

use burn::config::Config;
use burn::tensor::activation::sigmoid;
use burn::tensor::{Device, Tensor};

use crate::util::rng::Rng;

/// Reference section 3: mask ~ Bernoulli(keep_prob), temperature 1.
#[derive(Config, Debug)]
pub struct MeasurementConfig {
    /// Gumbel-sigmoid temperature.
    #[config(default = 1.0)]
    pub tau: f32,
}

/// A measured image and the probabilities behind it, all `[batch, 1, H, W]`.
#[derive(Debug, Clone)]
pub struct Measured {
    /// Probability that the ray returns.
    pub keep_prob: Tensor<4>,
    /// x_n: probability that the ray is dropped, 1 - keep_prob.
    pub drop_prob: Tensor<4>,
    /// Sampled mask in {0, 1} (1 = return); its gradient is the soft sample's.
    pub mask: Tensor<4>,
    /// x_G: mask * x_d + (1 - mask) * (-1), network units.
    pub x_measured: Tensor<4>,
}

impl MeasurementConfig {
    /// Sample the measurement. `x_d` is in network units ([-1, 1]); a dropped pixel becomes -1.
    ///
    /// # Shapes
    /// - x_d, keep_logit: `[batch, 1, H, W]`
    pub fn measure(&self, x_d: Tensor<4>, keep_logit: Tensor<4>, rng: &mut Rng) -> Measured {
        let device: Device = x_d.device();
        let u = rng.uniform_open_tensor(keep_logit.dims(), &device); // [batch, 1, H, W]
        let logistic = u.clone().log() - u.neg().add_scalar(1.0).log(); // log u - log(1 - u)
        let soft = sigmoid((keep_logit.clone() + logistic).div_scalar(self.tau)); // [batch, 1, H, W]
        let hard = soft.clone().detach().greater_elem(0.5).float(); // [batch, 1, H, W]
        // Straight-through: the value of `hard`, the gradient of `soft`.
        let mask = hard + (soft.clone() - soft.detach());
        let x_measured = (mask.clone() * x_d.add_scalar(1.0)).sub_scalar(1.0);
        let keep_prob = sigmoid(keep_logit);
        Measured {
            drop_prob: keep_prob.clone().neg().add_scalar(1.0),
            keep_prob,
            mask,
            x_measured,
        }
    }
}

/// Expected image without sampling: keep_prob * x_d + drop_prob * (-1) (for inspection).
pub fn expected_measurement(x_d: Tensor<4>, keep_logit: Tensor<4>) -> Tensor<4> {
    (sigmoid(keep_logit) * x_d.add_scalar(1.0)).sub_scalar(1.0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::util::tensor::tensor_to_vec;

    #[test]
    fn mask_is_binary_with_the_keep_frequency_and_passes_gradients() {
        let dev = Device::flex().autodiff();
        let n = 20_000;
        // keep_prob = sigmoid(1.0) = 0.731
        let logit = Tensor::<4>::ones([1, 1, 1, n], &dev).require_grad();
        let x_d = Tensor::<4>::zeros([1, 1, 1, n], &dev)
            .add_scalar(0.5)
            .require_grad();
        let m = MeasurementConfig::new().measure(x_d.clone(), logit.clone(), &mut Rng::new(1));
        let mask = tensor_to_vec(m.mask.clone());
        assert!(mask.iter().all(|v| *v == 0.0 || *v == 1.0));
        let freq = mask.iter().sum::<f32>() / n as f32;
        assert!((freq - 0.731).abs() < 0.015, "keep frequency {freq}");
        let xm = tensor_to_vec(m.x_measured.clone());
        assert!(xm.iter().zip(&mask).all(|(x, k)| if *k > 0.5 {
            (x - 0.5).abs() < 1e-6
        } else {
            (x + 1.0).abs() < 1e-6
        }));
        let drop = tensor_to_vec(m.drop_prob.clone());
        assert!((drop[0] - (1.0 - 0.731)).abs() < 1e-3);
        let grads = m.x_measured.sum().backward();
        let g_logit = logit.grad(&grads).expect("logit gradient");
        assert!(g_logit.abs().sum().into_scalar::<f32>() > 0.0);
        assert!(x_d.grad(&grads).is_some());
    }
}
