//! The parameter updates of GAN training beside the optimiser: the mean of the batch parts'
//! gradients, the ray-drop-head-only gradient mask, the generator's EMA and the adaptive
//! augmentation that keeps the circular structure of range images.

use burn::module::{Module, ModuleMapper, ModuleVisitor, Param};
use burn::optim::GradientsParams;
use burn::tensor::Tensor;

use crate::model::AnyGenerator;
use crate::model::data::DROPPED;
use crate::util::rng::Rng;
use crate::util::tensor::tensor_from;

/// The keep logit's output row in a generator head (row 0 is x_d before tanh).
const KEEP_LOGIT: usize = 1;

/// The gradients of the ray-drop logit alone: each synthesis block's head keeps the
/// gradient of its second output row (weight and bias), everything else has none, so
/// Adam leaves it exactly as it is.
pub(crate) fn drop_head_grads(g: &AnyGenerator, mut grads: GradientsParams) -> GradientsParams {
    let mut out = GradientsParams::new();
    let AnyGenerator::Implicit(generator) = g else {
        return out;
    };
    for head in generator.blocks.iter().map(|b| &b.head) {
        if let Some(w) = grads.remove::<2>(head.weight.id) {
            out.register(head.weight.id, keep_logit_only(w));
        }
        if let Some(b) = grads.remove::<1>(head.bias.id) {
            out.register(head.bias.id, keep_logit_only(b));
        }
    }
    out
}

/// A head parameter's gradient with every output row but the keep logit's zeroed.
fn keep_logit_only<const D: usize>(grad: Tensor<D>) -> Tensor<D> {
    let dims = grad.dims();
    let per_row = dims[1..].iter().product::<usize>();
    let mask: Vec<f32> = (0..dims[0] * per_row)
        .map(|i| if i / per_row == KEEP_LOGIT { 1.0 } else { 0.0 })
        .collect();
    let mask = tensor_from(mask, dims, &grad.device());
    grad * mask
}

/// The mean of the parts' gradients (each part's loss is a mean over its samples, so
/// the mean is the whole batch's gradient).
pub(crate) fn mean_grads<M: Module>(module: &M, parts: Vec<GradientsParams>) -> GradientsParams {
    struct Mean {
        parts: Vec<GradientsParams>,
        out: GradientsParams,
    }
    impl ModuleVisitor for Mean {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            let grads: Vec<Tensor<D>> = self
                .parts
                .iter_mut()
                .filter_map(|g| g.remove::<D>(param.id))
                .collect();
            let n = grads.len() as f32;
            if let Some(sum) = grads.into_iter().reduce(|a, b| a + b) {
                self.out.register(param.id, sum.div_scalar(n));
            }
        }
    }
    if parts.len() == 1 {
        return parts.into_iter().next().unwrap_or_default();
    }
    let mut mean = Mean {
        parts,
        out: GradientsParams::new(),
    };
    module.visit(&mut mean);
    mean.out
}

/// Random augmentation with probability `p` per operation and sample. Only operations that
/// keep the circular structure: circular translation and mirroring along azimuth, vertical
/// scaling, brightness and contrast of the returns (dropped pixels stay -1). Geometric parts
/// are one batched `A_b x_b B_b` product with host-built matrices, so gradients flow to fakes.
///
/// # Shapes
/// - x: `[batch, 1, H, W]` -> `[batch, 1, H, W]`
pub fn augment(x: Tensor<4>, p: f32, rng: &mut Rng) -> Tensor<4> {
    let [b, c, h, w] = x.dims();
    let device = x.device();
    let mut rows = vec![0f32; b * h * h];
    let mut cols = vec![0f32; b * w * w];
    let mut gain = vec![1f32; b];
    let mut offset = vec![0f32; b];
    for i in 0..b {
        // columns: out[j] = x[src(j)]
        let flip = rng.uniform() < p;
        let shift = if rng.uniform() < p { rng.below(w) } else { 0 };
        for j in 0..w {
            let k = (j + w - shift) % w;
            let src = if flip { w - 1 - k } else { k };
            cols[i * w * w + src * w + j] = 1.0;
        }
        // rows: vertical scale about the centre, linear interpolation, clamped borders
        let scale = if rng.uniform() < p {
            (rng.normal() * 0.2 * std::f32::consts::LN_2).exp()
        } else {
            1.0
        };
        let centre = (h as f32 - 1.0) * 0.5;
        for r in 0..h {
            let y = ((r as f32 - centre) / scale + centre).clamp(0.0, (h - 1) as f32);
            let y0 = y.floor() as usize;
            let y1 = (y0 + 1).min(h - 1);
            let t = y - y0 as f32;
            rows[i * h * h + r * h + y0] += 1.0 - t;
            rows[i * h * h + r * h + y1] += t;
        }
        if rng.uniform() < p {
            offset[i] = rng.normal() * 0.2;
        }
        if rng.uniform() < p {
            gain[i] = (rng.normal() * 0.5 * std::f32::consts::LN_2).exp();
        }
    }
    let a = tensor_from(rows, [b, 1, h, h], &device);
    let m = tensor_from(cols, [b, 1, w, w], &device);
    let valid = x.clone().greater_elem(DROPPED).float(); // [batch, 1, H, W]
    let x = a.clone().matmul(x).matmul(m.clone()); // [batch, 1, H, W]
    let valid = a.matmul(valid).matmul(m).greater_elem(0.5).float();
    let gain = tensor_from(gain, [b, 1, 1, 1], &device);
    let offset = tensor_from(offset, [b, 1, 1, 1], &device);
    // contrast scales the inverse depth of returns, brightness shifts it
    let y = (x.add_scalar(1.0) * gain).sub_scalar(1.0) + offset;
    let y = (y.add_scalar(1.0) * valid).sub_scalar(1.0);
    debug_assert_eq!(c, 1);
    y
}

/// Collects a module's float parameters (flattened, no autodiff) in visit order.
struct Collect(Vec<(Tensor<1>, bool)>);

impl ModuleVisitor for Collect {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        let t = param.val();
        let trainable = t.is_require_grad();
        self.0.push((t.inner().reshape([-1]), trainable));
    }
}

/// ema <- beta ema + (1 - beta) g for trainable tensors; fixed tensors (Fourier frequencies,
/// w_avg) are copied.
struct Lerp {
    src: std::vec::IntoIter<(Tensor<1>, bool)>,
    beta: f32,
}

impl ModuleMapper for Lerp {
    fn map_float<const D: usize>(&mut self, param: Param<Tensor<D>>) -> Param<Tensor<D>> {
        let Some((src, trainable)) = self.src.next() else {
            return param;
        };
        let beta = self.beta;
        param.map(|e| {
            let src = src.reshape(e.shape());
            if trainable {
                e.mul_scalar(beta) + src.mul_scalar(1.0 - beta)
            } else {
                src
            }
        })
    }
}

/// `g` must live on an autodiff device (the training module): trainability is read from it.
pub fn ema_update<M: Module>(ema: M, g: &M, beta: f32) -> M {
    let mut c = Collect(Vec::new());
    g.visit(&mut c);
    ema.map(&mut Lerp {
        src: c.0.into_iter(),
        beta,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::Arch;
    use crate::model::baseline::ConvGeneratorConfig;
    use crate::model::generator::GeneratorConfig;
    use crate::train::{TrainConfig, init_generator};
    use crate::util::tensor::tensor_to_vec;
    use burn::tensor::Device;

    #[test]
    fn augment_keeps_drops_and_identity_at_p0() {
        let dev = Device::flex();
        let mut rng = Rng::new(1);
        let mut v = rng.uniform_vec(2 * 8 * 16);
        for (i, x) in v.iter_mut().enumerate() {
            if i % 5 == 0 {
                *x = -1.0;
            }
        }
        let x = tensor_from(v.clone(), [2, 1, 8, 16], &dev);
        let same = tensor_to_vec(augment(x.clone(), 0.0, &mut rng));
        assert!(same.iter().zip(&v).all(|(a, b)| (a - b).abs() < 1e-6));
        // A pure circular shift/flip keeps the number of dropped pixels.
        let y = tensor_to_vec(augment(x, 1.0, &mut rng));
        assert_eq!(y.len(), v.len());
        assert!(y.iter().all(|v| *v >= -1.0 - 1e-6));
    }

    #[test]
    fn ema_moves_towards_the_generator() {
        // The source is a training (autodiff) module: that is where trainability is known.
        let dev = Device::flex().autodiff();
        let cfg = TrainConfig::new().with_generator(
            GeneratorConfig::new()
                .with_mapping(
                    crate::model::generator::MappingConfig::new()
                        .with_d_z(4)
                        .with_d_w(4),
                )
                .with_channels(vec![4])
                .with_n_freq(vec![2])
                .with_lh(vec![3])
                .with_lw(vec![2]),
        );
        let a = init_generator(&cfg, &dev);
        let b = init_generator(
            &cfg.clone()
                .with_generator(cfg.generator.clone().with_seed(9)),
            &dev,
        );
        let mid = ema_update(a.clone(), &b, 0.5);
        let (AnyGenerator::Implicit(a), AnyGenerator::Implicit(b), AnyGenerator::Implicit(m)) =
            (a, b, mid)
        else {
            panic!("implicit expected");
        };
        let wa = tensor_to_vec(a.blocks[0].conv0.weight.val());
        let wb = tensor_to_vec(b.blocks[0].conv0.weight.val());
        let wm = tensor_to_vec(m.blocks[0].conv0.weight.val());
        for i in 0..wa.len() {
            assert!((wm[i] - 0.5 * (wa[i] + wb[i])).abs() < 1e-6);
        }
        // Fixed tensors are copied, not averaged.
        assert_eq!(
            tensor_to_vec(m.blocks[0].fourier.b_theta.val()),
            tensor_to_vec(b.blocks[0].fourier.b_theta.val())
        );
    }

    #[test]
    fn the_mean_of_the_parts_gradients_is_the_whole_batch_gradient() {
        let dev = Device::flex().autodiff();
        let cfg = TrainConfig::new()
            .with_arch(Arch::Vanilla)
            .with_conv_generator(
                ConvGeneratorConfig::new()
                    .with_d_z(6)
                    .with_channels(vec![8, 4])
                    .with_base_height(2)
                    .with_base_width(4),
            );
        let g = init_generator(&cfg, &dev);
        let z = Rng::new(5).normal_tensor([4, 6], &dev);
        let grads_of = |g: &AnyGenerator, z: Tensor<2>| {
            let g = g.clone().fork(&dev);
            let (out, _) = g.generate(z, None, None);
            let loss = out.x_d.powi_scalar(2).mean();
            GradientsParams::from_grads(loss.backward(), &g)
        };
        let whole = grads_of(&g, z.clone());
        let parts = (0..2)
            .map(|k| grads_of(&g, z.clone().narrow(0, 2 * k, 2)))
            .collect();
        let mean = mean_grads(&g, parts);
        let AnyGenerator::Conv(conv) = &g else {
            panic!("conv generator expected");
        };
        let id = conv.ups[0].weight.id;
        let (a, b) = (whole.get::<4>(id), mean.get::<4>(id));
        let (a, b) = (tensor_to_vec(a.unwrap()), tensor_to_vec(b.unwrap()));
        assert!(
            a.iter().any(|x| x.abs() > 1e-6),
            "a gradient that is zero tests nothing"
        );
        for (x, y) in a.iter().zip(&b) {
            assert!((x - y).abs() <= 1e-5 * (1.0 + x.abs()), "{x} vs {y}");
        }
    }
}
