//! A small fully connected network (ReLU hidden layers, a linear output) with its own
//! backward pass and Adam. For per-pixel models of a few thousand weights, evaluated on
//! tens of thousands of pixels at once, where a tensor library's per-operation overhead
//! would cost more than the arithmetic; plain data, so it serialises as JSON.

use serde::{Deserialize, Serialize};

use super::matmul::{View, matmul};
use super::rng::Rng;

/// One layer: `outputs x inputs` weights (row-major) and a bias per output.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Dense {
    pub inputs: usize,
    pub outputs: usize,
    pub weight: Vec<f32>,
    pub bias: Vec<f32>,
}

impl Dense {
    /// `y = W x + b` for `n` samples stored one after another in `x`: one matrix product
    /// for all of them.
    fn forward(&self, x: &[f32], n: usize) -> Vec<f32> {
        let (i, o) = (self.inputs, self.outputs);
        let mut y: Vec<f32> = self.bias.iter().copied().cycle().take(n * o).collect();
        let weight_t = View::new(&self.weight, o, i).t();
        matmul(View::new(&x[..n * i], n, i), weight_t, &mut y, true);
        y
    }

    fn is_consistent(&self) -> bool {
        self.weight.len() == self.inputs * self.outputs && self.bias.len() == self.outputs
    }
}

/// Layers applied in turn, ReLU between them.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Mlp {
    pub layers: Vec<Dense>,
}

/// Every layer's input, as kept by [`Mlp::forward_kept`] for the backward pass; the last
/// entry is the output.
pub struct Activations {
    values: Vec<Vec<f32>>,
    n: usize,
}

impl Activations {
    pub fn output(&self) -> &[f32] {
        self.values.last().map_or(&[], Vec::as_slice)
    }
}

impl Mlp {
    /// Layer sizes `sizes[0] -> sizes[1] -> ...`, He-initialised; the last layer starts at
    /// zero, so a fresh network outputs 0 (a correction network starts as "no correction").
    pub fn new(sizes: &[usize], rng: &mut Rng) -> Mlp {
        let last = sizes.len().saturating_sub(2);
        let layers = sizes
            .windows(2)
            .enumerate()
            .map(|(k, io)| {
                let (i, o) = (io[0], io[1]);
                let scale = if k == last {
                    0.0
                } else {
                    (2.0 / i as f32).sqrt()
                };
                Dense {
                    inputs: i,
                    outputs: o,
                    weight: rng.normal_vec(i * o).iter().map(|w| w * scale).collect(),
                    bias: vec![0.0; o],
                }
            })
            .collect();
        Mlp { layers }
    }

    pub fn inputs(&self) -> usize {
        self.layers.first().map_or(0, |l| l.inputs)
    }

    pub fn outputs(&self) -> usize {
        self.layers.last().map_or(0, |l| l.outputs)
    }

    /// Layers chain (each one's inputs are the previous one's outputs) and every weight
    /// vector has its stated size: checked after loading a file.
    /// Whether it is consistent and maps `inputs` values to `outputs`.
    pub fn takes(&self, inputs: usize, outputs: usize) -> bool {
        self.is_consistent() && self.inputs() == inputs && self.outputs() == outputs
    }

    pub fn is_consistent(&self) -> bool {
        !self.layers.is_empty()
            && self.layers.iter().all(Dense::is_consistent)
            && self.layers.windows(2).all(|p| p[0].outputs == p[1].inputs)
    }

    /// The outputs for `x.len() / inputs` samples.
    pub fn forward(&self, x: &[f32]) -> Vec<f32> {
        let n = x.len() / self.inputs().max(1);
        let mut h = self.layers[0].forward(x, n);
        for layer in &self.layers[1..] {
            relu(&mut h);
            h = layer.forward(&h, n);
        }
        h
    }

    /// As [`Mlp::forward`], keeping what the backward pass needs.
    pub fn forward_kept(&self, x: &[f32]) -> Activations {
        let n = x.len() / self.inputs().max(1);
        let mut values = vec![x.to_vec()];
        for (k, layer) in self.layers.iter().enumerate() {
            let mut h = layer.forward(&values[k], n);
            if k + 1 < self.layers.len() {
                relu(&mut h);
            }
            values.push(h);
        }
        Activations { values, n }
    }

    /// The gradient of a loss with respect to every weight, given its gradient with respect
    /// to the outputs (`n x outputs`). Same layout as the network.
    pub fn backward(&self, acts: &Activations, output_grad: &[f32]) -> Mlp {
        let mut grads = self.zeros();
        let mut g = output_grad.to_vec();
        for (k, layer) in self.layers.iter().enumerate().rev() {
            let x = &acts.values[k];
            let (i, o) = (layer.inputs, layer.outputs);
            let grad = &mut grads.layers[k];
            let mut gx = vec![0.0f32; acts.n * i];
            for s in 0..acts.n {
                let (gs, xs) = (&g[s * o..(s + 1) * o], &x[s * i..(s + 1) * i]);
                let gxs = &mut gx[s * i..(s + 1) * i];
                for (j, &gj) in gs.iter().enumerate() {
                    if gj == 0.0 {
                        continue;
                    }
                    grad.bias[j] += gj;
                    let w = &layer.weight[j * i..(j + 1) * i];
                    let gw = &mut grad.weight[j * i..(j + 1) * i];
                    for t in 0..i {
                        gw[t] += gj * xs[t];
                        gxs[t] += gj * w[t];
                    }
                }
            }
            if k > 0 {
                // Through the ReLU that made this layer's input.
                for (gv, xv) in gx.iter_mut().zip(x) {
                    if *xv <= 0.0 {
                        *gv = 0.0;
                    }
                }
            }
            g = gx;
        }
        grads
    }

    fn zeros(&self) -> Mlp {
        let mut z = self.clone();
        for l in &mut z.layers {
            l.weight.fill(0.0);
            l.bias.fill(0.0);
        }
        z
    }

    fn params_mut(&mut self) -> impl Iterator<Item = &mut f32> {
        self.layers
            .iter_mut()
            .flat_map(|l| l.weight.iter_mut().chain(l.bias.iter_mut()))
    }

    fn params(&self) -> impl Iterator<Item = &f32> {
        self.layers
            .iter()
            .flat_map(|l| l.weight.iter().chain(l.bias.iter()))
    }
}

fn relu(h: &mut [f32]) {
    for v in h {
        *v = v.max(0.0);
    }
}

/// Adam (Kingma and Ba) over an [`Mlp`]'s weights.
#[derive(Debug, Clone)]
pub struct Adam(super::adam::Adam);

impl Adam {
    pub fn new(net: &Mlp) -> Adam {
        Adam(super::adam::Adam::new(net.params().count()))
    }

    pub fn step(&mut self, net: &mut Mlp, grads: &Mlp, lr: f32) {
        self.0.step(net.params_mut(), grads.params(), lr);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn loss(net: &Mlp, x: &[f32], target: &[f32]) -> f32 {
        net.forward(x)
            .iter()
            .zip(target)
            .map(|(y, t)| 0.5 * (y - t) * (y - t))
            .sum()
    }

    #[test]
    fn backward_matches_finite_differences() {
        let mut rng = Rng::new(3);
        let mut net = Mlp::new(&[3, 5, 4, 2], &mut rng);
        // A non-zero last layer, so every gradient path is exercised.
        for w in &mut net.layers[2].weight {
            *w = rng.normal();
        }
        let x = rng.normal_vec(4 * 3);
        let target = rng.normal_vec(4 * 2);
        let acts = net.forward_kept(&x);
        let out_grad: Vec<f32> = acts
            .output()
            .iter()
            .zip(&target)
            .map(|(y, t)| y - t)
            .collect();
        let grads = net.backward(&acts, &out_grad);
        let analytic: Vec<f32> = grads.params().copied().collect();
        let eps = 1e-3;
        for (k, &a) in analytic.iter().enumerate() {
            let mut up = net.clone();
            *up.params_mut().nth(k).unwrap() += eps;
            let mut down = net.clone();
            *down.params_mut().nth(k).unwrap() -= eps;
            let numeric = (loss(&up, &x, &target) - loss(&down, &x, &target)) / (2.0 * eps);
            assert!(
                (a - numeric).abs() < 2e-2 * (1.0 + numeric.abs()),
                "{k}: {a} vs {numeric}"
            );
        }
    }

    #[test]
    fn adam_fits_a_nonlinear_function() {
        let mut rng = Rng::new(5);
        let mut net = Mlp::new(&[1, 16, 1], &mut rng);
        let mut opt = Adam::new(&net);
        let x: Vec<f32> = (0..64).map(|k| k as f32 / 32.0 - 1.0).collect();
        let target: Vec<f32> = x.iter().map(|v| v.abs()).collect();
        let before = loss(&net, &x, &target);
        for _ in 0..2000 {
            let acts = net.forward_kept(&x);
            let g: Vec<f32> = acts
                .output()
                .iter()
                .zip(&target)
                .map(|(y, t)| y - t)
                .collect();
            let grads = net.backward(&acts, &g);
            opt.step(&mut net, &grads, 0.01);
        }
        let after = loss(&net, &x, &target);
        assert!(after < 0.01 * before, "{before} -> {after}");
    }

    #[test]
    fn a_fresh_network_outputs_zero_and_round_trips_as_json() {
        let net = Mlp::new(&[4, 8, 1], &mut Rng::new(1));
        assert_eq!(net.forward(&[1.0, -2.0, 3.0, 0.5]), vec![0.0]);
        let back: Mlp = serde_json::from_str(&serde_json::to_string(&net).unwrap()).unwrap();
        assert_eq!(back, net);
        assert!(back.is_consistent());
    }
}
