//! Pivotal tuning by hand on the CPU: the implicit generator's forward and backward pass at
//! batch 1 with w frozen, and Adam over every tuned weight.
//!
//! The same function, loss and optimiser as the autodiff path ([`super::invert`]) (a test
//! holds the two level), written as a few passes per synthesis block over host slices. Through
//! autodiff a batch-1 tuning step spends most of its time creating, copying and walking
//! per-op tensors rather than multiplying (BENCHMARKS.md, "Where a `fast` decode's time goes").
//!
//! A modulated layer with style s and scaled weight W computes y = x (W diag(s))^T, so its
//! products use one per-step matrix Wm = W diag(s), and the backward pass needs no per-pixel
//! copy of x s: with G = gy^T x, dL/dW = G diag(s) and dL/ds_k = sum_o W_ok G_ok, plus the
//! demodulation's terms.

use std::f32::consts::SQRT_2;
use std::ops::Range;
use std::sync::Arc;

use burn::module::Param;
use burn::tensor::{Device, Tensor};

mod kernels;

use super::invert::{Inverted, Schedule};
use super::loss::reconstruction_loss_grad;
use crate::model::generator::{Generator, GridCache};
use crate::model::layers::ModulatedLinear;
use crate::util::adam::Adam;
use crate::util::matmul::{View, matmul};
use crate::util::tensor::{tensor_from, tensor_to_vec};
use kernels::{
    scale_shift_activate, scale_shift_activate_backward, upsample2x, upsample2x_adjoint,
};

/// Slopes of LeakyReLU(0.2) * sqrt(2) ([`crate::model::layers::lrelu_gain`]).
const POS: f32 = SQRT_2;
const NEG: f32 = 0.2 * SQRT_2;

/// Whether [`Tuning`] runs `schedule` on `generator`: pivotal tuning alone (no steps on w, no
/// coarse steps), and no local 3x3 paths. Anything else takes the autodiff path.
pub fn supports(generator: &Generator, schedule: &Schedule) -> bool {
    schedule.w_steps == 0
        && schedule.coarse_steps.is_empty()
        && schedule.tune_w_lr == 0.0
        && covers(generator)
}

/// Whether the hand-written passes cover `generator`'s layers (no local 3x3 paths).
fn covers(generator: &Generator) -> bool {
    generator.blocks.iter().all(|b| b.local.is_none())
}

/// `generator`'s two heads at latent `w` on `cache`'s grid, by the forward pass the tuning
/// runs: x_d (network units, after the output gain and tanh) and the keep logit (after the
/// output gain), `H*W` each, row-major; `None` where the passes do not cover the generator.
/// The same rendering as [`Generator::render`] without a subgrid shift, at batch 1 and
/// without burn's per-op tensors, which at a sensor's full resolution cost more than the
/// products themselves.
pub fn render(generator: &Generator, cache: &GridCache, w: &[f32]) -> Option<(Vec<f32>, Vec<f32>)> {
    let (heads, gain) = heads(generator, cache, w, 2)?;
    let x_d = heads.iter().step_by(2).map(|h| (h * gain).tanh()).collect();
    let keep_logit = heads.iter().skip(1).step_by(2).map(|h| h * gain).collect();
    Some((x_d, keep_logit))
}

/// x_d alone, as [`render`] gives it, without the keep head's products.
pub fn render_x_d(generator: &Generator, cache: &GridCache, w: &[f32]) -> Option<Vec<f32>> {
    let (heads, gain) = heads(generator, cache, w, 1)?;
    Some(heads.iter().map(|h| (h * gain).tanh()).collect())
}

/// The first `outputs` summed heads and the output gain ([`Net::forward`]).
fn heads(
    generator: &Generator,
    cache: &GridCache,
    w: &[f32],
    outputs: usize,
) -> Option<(Vec<f32>, f32)> {
    if !covers(generator) {
        return None;
    }
    let mut net = Net::read(generator, cache, false);
    Some((net.forward(w, outputs), net.output_gain))
}

/// Pivotal tuning of a copy of a generator at a frozen latent w against one observation. It
/// can stop after any step, hand on the weights reached so far ([`Tuning::weights`]) and go
/// on later from exactly where it stopped.
pub struct Tuning {
    net: Net,
    /// The tuned weights: runs of indices into the flat parameter vector.
    moved: Vec<Range<usize>>,
    adam: Adam,
    schedule: Schedule,
    target: Vec<f32>,
    mask: Vec<f32>,
    w: Vec<f32>,
    losses: Vec<f32>,
}

impl Tuning {
    /// Tuning of a copy of `generator` at `w` against `target` and `mask` (the model grid's
    /// `H*W` pixels, network units and {0, 1}), before its first step.
    pub fn new(
        generator: &Generator,
        cache: &GridCache,
        target: &[f32],
        mask: &[f32],
        w: Vec<f32>,
        schedule: &Schedule,
    ) -> Tuning {
        let net = Net::read(generator, cache, true);
        let moved = net.moved(schedule.keep_heads_and_biases);
        Tuning {
            adam: Adam::new(moved.iter().map(Range::len).sum()),
            moved,
            net,
            schedule: schedule.clone(),
            target: target.to_vec(),
            mask: mask.to_vec(),
            w,
            losses: Vec::with_capacity(schedule.tune_steps),
        }
    }

    /// Steps done so far.
    pub fn steps(&self) -> usize {
        self.losses.len()
    }

    /// Runs the steps up to `step` (at most the schedule's).
    pub fn run_to(&mut self, step: usize) {
        let total = self.schedule.tune_steps;
        for step in self.steps()..step.min(total) {
            let lr = self.schedule.tuning_rate(step, total);
            let (loss, grads) = (self.net).loss_and_gradients(
                &self.w,
                &self.target,
                &self.mask,
                self.schedule.pyramid_levels,
            );
            self.losses.push(loss);
            (self.adam).step_runs(&mut self.net.params, &grads, &self.moved, lr as f32);
        }
    }

    /// `generator` with the weights tuned so far.
    pub fn weights(&self, generator: &Generator) -> Generator {
        self.net.write(generator)
    }

    /// The rest of the schedule's steps, and the result.
    pub fn finish(mut self, generator: &Generator) -> Inverted {
        self.run_to(self.schedule.tune_steps);
        Inverted {
            generator: self.net.write(generator),
            w: self.w,
            losses: self.losses,
        }
    }
}

/// The runs of consecutive `true` indices, in order.
fn runs(flags: &[bool]) -> Vec<Range<usize>> {
    let mut out: Vec<Range<usize>> = Vec::new();
    for (i, _) in flags.iter().enumerate().filter(|(_, f)| **f) {
        match out.last_mut() {
            Some(r) if r.end == i => r.end = i + 1,
            _ => out.push(i..i + 1),
        }
    }
    out
}

/// Where one modulated layer's weights sit in the flat parameter vector, and its constants.
struct Layer {
    d_in: usize,
    d_out: usize,
    demodulate: bool,
    activate: bool,
    affine_gain: f32,
    affine_lr_mul: f32,
    weight_gain: f32,
    /// `[d_in, d_w]`
    affine_weight: Range<usize>,
    /// `[d_in]`
    affine_bias: Range<usize>,
    /// `[d_out, d_in]`
    weight: Range<usize>,
    /// `[d_out]`
    bias: Range<usize>,
}

/// A layer's values for one step: style s, scaled weight W, Wm = W diag(s), demodulation d.
#[derive(Default)]
struct Modulated {
    s: Vec<f32>,
    ws: Vec<f32>,
    wm: Vec<f32>,
    d: Vec<f32>,
}

impl Layer {
    fn read(layer: &ModulatedLinear, params: &mut Vec<f32>) -> Layer {
        let mut push = |v: Vec<f32>| {
            let start = params.len();
            params.extend(v);
            start..params.len()
        };
        let [d_out, d_in] = layer.weight.dims();
        Layer {
            d_in,
            d_out,
            demodulate: layer.demodulate,
            activate: layer.activate,
            affine_gain: layer.affine.weight_gain,
            affine_lr_mul: layer.affine.lr_mul,
            weight_gain: layer.weight_gain,
            affine_weight: push(tensor_to_vec(layer.affine.weight.val())),
            affine_bias: push(tensor_to_vec(layer.affine.bias.val())),
            weight: push(tensor_to_vec(layer.weight.val())),
            bias: push(tensor_to_vec(layer.bias.val())),
        }
    }

    fn write(&self, layer: &mut ModulatedLinear, params: &[f32], device: &Device) {
        let d_w = self.affine_weight.len() / self.d_in;
        let values = |r: &Range<usize>| params[r.clone()].to_vec();
        let t2 = |r: &Range<usize>, shape| tensor_from(values(r), shape, device);
        let t1 = |r: &Range<usize>| tensor_from(values(r), [r.len()], device);
        let affine = &mut layer.affine;
        affine.weight = set(&affine.weight, t2(&self.affine_weight, [self.d_in, d_w]));
        affine.bias = set(&affine.bias, t1(&self.affine_bias));
        layer.weight = set(&layer.weight, t2(&self.weight, [self.d_out, self.d_in]));
        layer.bias = set(&layer.bias, t1(&self.bias));
    }

    fn modulate(&self, p: &[f32], w: &[f32]) -> Modulated {
        let d_w = w.len();
        let aw = &p[self.affine_weight.clone()];
        let ab = &p[self.affine_bias.clone()];
        let s: Vec<f32> = (0..self.d_in)
            .map(|k| {
                let row = &aw[k * d_w..(k + 1) * d_w];
                let dot: f32 = row.iter().zip(w).map(|(a, b)| a * b).sum();
                dot * self.affine_gain + ab[k] * self.affine_lr_mul
            })
            .collect();
        let ws: Vec<f32> = p[self.weight.clone()]
            .iter()
            .map(|v| v * self.weight_gain)
            .collect();
        let wm: Vec<f32> = (ws.chunks_exact(self.d_in))
            .flat_map(|row| row.iter().zip(&s).map(|(v, s)| v * s))
            .collect();
        let d = (0..self.d_out)
            .map(|o| {
                if !self.demodulate {
                    return 1.0;
                }
                let row = &wm[o * self.d_in..(o + 1) * self.d_in];
                1.0 / (row.iter().map(|v| v * v).sum::<f32>() + 1e-8).sqrt()
            })
            .collect();
        Modulated { s, ws, wm, d }
    }

    /// The layer's output from its product y (`[pixels, d_out]`, before demodulation).
    fn output(&self, m: &Modulated, p: &[f32], y: &[f32], out: &mut [f32]) {
        let (bias, d) = (&p[self.bias.clone()], &m.d[..self.d_out]);
        scale_shift_activate(y, (d, bias), self.slopes(), out);
    }

    /// The activation's slopes above and below 0 (1 without one).
    fn slopes(&self) -> (f32, f32) {
        if self.activate {
            (POS, NEG)
        } else {
            (1.0, 1.0)
        }
    }

    /// Back through [`Layer::output`]: turns `g` (the output's gradient) into the product's in
    /// place, and returns the gradients of the demodulation coefficients and of the bias.
    fn output_backward(
        &self,
        m: &Modulated,
        p: &[f32],
        y: &[f32],
        g: &mut [f32],
    ) -> (Vec<f32>, Vec<f32>) {
        let (bias, d) = (&p[self.bias.clone()], &m.d[..self.d_out]);
        let mut gd = vec![0.0f32; self.d_out];
        let mut gb = vec![0.0f32; self.d_out];
        scale_shift_activate_backward(y, (d, bias), self.slopes(), g, (&mut gd, &mut gb));
        (gd, gb)
    }

    /// The weights' gradients, into `grads`, from G = gy^T x (`[d_out, d_in]`, gy the product's
    /// gradient) and the output's `gd`, `gb`.
    fn weight_gradients(
        &self,
        m: &Modulated,
        w: &[f32],
        (g, gd, gb): (&[f32], &[f32], &[f32]),
        grads: &mut [f32],
    ) {
        let d_in = self.d_in;
        let mut gs = vec![0.0f32; d_in];
        for o in 0..self.d_out {
            // d = (sum_k (s_k W_ok)^2 + eps)^(-1/2)
            let gr = if self.demodulate {
                -0.5 * gd[o] * m.d[o].powi(3)
            } else {
                0.0
            };
            let row = o * d_in..(o + 1) * d_in;
            let start = self.weight.start + row.start;
            let g_weight = &mut grads[start..start + d_in];
            let terms = m.s.iter().zip(&m.ws[row.clone()]).zip(&g[row]);
            for (((s, ws), gok), (gs, gw)) in terms.zip(gs.iter_mut().zip(g_weight)) {
                *gs += ws * gok + gr * 2.0 * s * ws * ws;
                *gw += (gok * s + gr * 2.0 * s * s * ws) * self.weight_gain;
            }
            grads[self.bias.start + o] += gb[o];
        }
        let affine = grads[self.affine_weight.clone()].chunks_exact_mut(w.len());
        for (row, gk) in affine.zip(&gs) {
            row.iter_mut()
                .zip(w)
                .for_each(|(g, wj)| *g += gk * self.affine_gain * wj);
        }
        let affine_bias = &mut grads[self.affine_bias.clone()];
        for (g, gk) in affine_bias.iter_mut().zip(&gs) {
            *g += gk * self.affine_lr_mul;
        }
    }
}

fn set<const D: usize>(param: &Param<Tensor<D>>, value: Tensor<D>) -> Param<Tensor<D>> {
    param.clone().map(|_| value)
}

/// One synthesis block: its three layers, its level's Fourier basis and sizes.
struct Block {
    conv0: Layer,
    conv1: Layer,
    head: Layer,
    /// `[h*w, 2F]`, shared with the grid's cache
    basis: Arc<[f32]>,
    size: (usize, usize),
}

impl Block {
    fn pixels(&self) -> usize {
        self.size.0 * self.size.1
    }

    fn channels(&self) -> usize {
        self.conv1.d_out
    }

    /// Channels of conv0's input that come from the previous block.
    fn previous_channels(&self) -> usize {
        self.conv0.d_in - self.basis.len() / self.pixels()
    }
}

/// A block's buffers, kept from step to step: what the forward pass keeps for the backward one
/// (this step's modulations, conv0's and conv1's products before demodulation and their outputs)
/// and the gradients of the two outputs. `[pixels, ch]` each.
#[derive(Default)]
struct Pass {
    m0: Modulated,
    m1: Modulated,
    mh: Modulated,
    y0: Vec<f32>,
    a0: Vec<f32>,
    y1: Vec<f32>,
    a1: Vec<f32>,
    g_a0: Vec<f32>,
    g_a1: Vec<f32>,
}

impl Pass {
    /// A block's buffers for a tuning: the forward pass's and the backward pass's.
    fn new(block: &Block) -> Pass {
        let len = block.pixels() * block.channels();
        Pass {
            m0: Modulated::default(),
            m1: Modulated::default(),
            mh: Modulated::default(),
            y0: vec![0.0; len],
            a0: vec![0.0; len],
            y1: vec![0.0; len],
            a1: vec![0.0; len],
            g_a0: vec![0.0; len],
            g_a1: vec![0.0; len],
        }
    }
}

/// The generator as flat tuned weights and host-side blocks, with each block's buffers.
struct Net {
    params: Vec<f32>,
    blocks: Vec<Block>,
    work: Vec<Pass>,
    output_gain: f32,
}

impl Net {
    /// The weights of `generator` and the bases of `cache`; with `backward` each block's
    /// buffers for a tuning, kept from step to step, else none (a rendering makes each
    /// block's buffers as it goes and frees them when the next block has read them).
    fn read(generator: &Generator, cache: &GridCache, backward: bool) -> Net {
        let mut params = Vec::new();
        let levels = cache.levels.iter().zip(cache.host_bases());
        let blocks: Vec<Block> = (generator.blocks.iter().zip(levels))
            .map(|(block, (level, basis))| Block {
                conv0: Layer::read(&block.conv0, &mut params),
                conv1: Layer::read(&block.conv1, &mut params),
                head: Layer::read(&block.head, &mut params),
                basis: basis.clone(),
                size: (level.height, level.width),
            })
            .collect();
        Net {
            params,
            work: (blocks.iter())
                .map(|b| {
                    if backward {
                        Pass::new(b)
                    } else {
                        Pass::default()
                    }
                })
                .collect(),
            blocks,
            output_gain: generator.output_gain,
        }
    }

    /// The runs of flat weights that pivotal tuning moves: all, or with `keep_heads_and_biases`
    /// the synthesis layers' weights and style maps only ([`Schedule::keep_heads_and_biases`]).
    fn moved(&self, keep_heads_and_biases: bool) -> Vec<Range<usize>> {
        let mut moved = vec![true; self.params.len()];
        if keep_heads_and_biases {
            for block in &self.blocks {
                for r in [&block.conv0.bias, &block.conv1.bias] {
                    moved[r.clone()].fill(false);
                }
                let head = &block.head;
                for r in [
                    &head.affine_weight,
                    &head.affine_bias,
                    &head.weight,
                    &head.bias,
                ] {
                    moved[r.clone()].fill(false);
                }
            }
        }
        runs(&moved)
    }

    fn write(&self, generator: &Generator) -> Generator {
        let device = generator.mapping.w_avg.val().device();
        let mut out = generator.clone();
        for (block, layout) in out.blocks.iter_mut().zip(&self.blocks) {
            layout.conv0.write(&mut block.conv0, &self.params, &device);
            layout.conv1.write(&mut block.conv1, &self.params, &device);
            layout.head.write(&mut block.head, &self.params, &device);
        }
        out
    }

    /// The forward pass into the blocks' buffers; returns the summed heads' first `outputs`
    /// channels at the finest level (`[pixels, outputs]`, before the output gain): 1 is the
    /// inverse-depth channel alone (before tanh), 2 adds the keep logit.
    fn forward(&mut self, w: &[f32], outputs: usize) -> Vec<f32> {
        let Net {
            params: p,
            blocks,
            work,
            ..
        } = self;
        let mut heads: Vec<f32> = Vec::new();
        for (i, block) in blocks.iter().enumerate() {
            let (done, rest) = work.split_at_mut(i);
            let pass = &mut rest[0];
            let (n, c, c_x) = (block.pixels(), block.channels(), block.previous_channels());
            let (d_in, two_f) = (block.conv0.d_in, block.conv0.d_in - c_x);
            // A rendering's buffers are made for this block alone ([`Net::read`]).
            let rendering = pass.y0.is_empty();
            if rendering {
                for b in [&mut pass.y0, &mut pass.a0, &mut pass.y1, &mut pass.a1] {
                    *b = vec![0.0; n * c];
                }
                // g_a0 is the previous level's product before upsampling, a quarter the size.
                let previous = i.checked_sub(1).map_or(0, |k| blocks[k].pixels());
                pass.g_a0 = vec![0.0; previous * c];
            }
            pass.m0 = block.conv0.modulate(p, w);
            let wm_pe = View::columns(&pass.m0.wm, c, d_in, c_x, two_f).t();
            matmul(
                View::new(&block.basis, n, two_f),
                wm_pe,
                &mut pass.y0,
                false,
            );
            if let Some(prev) = done.last() {
                // The product at the previous level, then upsampled (the two commute); g_a0
                // is free until the backward pass.
                let (hp, wp) = blocks[i - 1].size;
                let y_x = &mut pass.g_a0[..hp * wp * c];
                let wm_x = View::columns(&pass.m0.wm, c, d_in, 0, c_x).t();
                matmul(View::new(&prev.a1, hp * wp, c_x), wm_x, y_x, false);
                let up = upsample2x(y_x, (hp, wp), c);
                pass.y0.iter_mut().zip(&up).for_each(|(y, u)| *y += u);
                heads = upsample2x(&heads, (hp, wp), outputs);
            }
            block.conv0.output(&pass.m0, p, &pass.y0, &mut pass.a0);
            pass.m1 = block.conv1.modulate(p, w);
            let wm1 = View::new(&pass.m1.wm, c, c).t();
            matmul(View::new(&pass.a0, n, c), wm1, &mut pass.y1, false);
            block.conv1.output(&pass.m1, p, &pass.y1, &mut pass.a1);
            pass.mh = block.head.modulate(p, w);
            let mut head = vec![0.0f32; n * outputs];
            let wm_h = View::new(&pass.mh.wm[..c * outputs], outputs, c).t();
            matmul(View::new(&pass.a1, n, c), wm_h, &mut head, false);
            let bias = p[block.head.bias.start..][..outputs].iter().cycle();
            heads = if heads.is_empty() {
                head.iter().zip(bias).map(|(h, b)| h + b).collect()
            } else {
                let sums = heads.iter().zip(&head).zip(bias);
                sums.map(|((u, h), b)| u + h + b).collect()
            };
            if rendering {
                for b in [&mut pass.y0, &mut pass.a0, &mut pass.y1, &mut pass.g_a0] {
                    *b = Vec::new();
                }
                if let Some(prev) = done.last_mut() {
                    prev.a1 = Vec::new();
                }
            }
        }
        heads
    }

    /// The reconstruction loss at latent `w` and its gradient for every tuned weight.
    fn loss_and_gradients(
        &mut self,
        w: &[f32],
        target: &[f32],
        mask: &[f32],
        levels: usize,
    ) -> (f32, Vec<f32>) {
        let heads = self.forward(w, 1);
        let x_net: Vec<f32> = heads
            .iter()
            .map(|h| (h * self.output_gain).tanh())
            .collect();
        let size = self.blocks.last().expect("a generator has blocks").size;
        let (loss, g_x) = reconstruction_loss_grad(&x_net, target, mask, size, levels);
        let g_heads: Vec<f32> = (g_x.iter().zip(&x_net))
            .map(|(g, x)| g * (1.0 - x * x) * self.output_gain)
            .collect();
        (loss, self.backward(w, g_heads))
    }

    /// The backward pass from the gradient of the finest summed heads.
    fn backward(&mut self, w: &[f32], mut g_heads: Vec<f32>) -> Vec<f32> {
        let Net {
            params: p,
            blocks,
            work,
            ..
        } = self;
        let mut grads = vec![0.0f32; p.len()];
        for (i, block) in blocks.iter().enumerate().rev() {
            let (below, rest) = work.split_at_mut(i);
            let pass = &mut rest[0];
            let (n, c, c_x) = (block.pixels(), block.channels(), block.previous_channels());
            let (d_in, two_f) = (block.conv0.d_in, block.conv0.d_in - c_x);

            // Head: only its inverse-depth channel reaches the loss. g_a1 already holds the
            // next block's part, except in the last block.
            let g_heads_v = View::new(&g_heads, n, 1);
            let wm_h = View::new(&pass.mh.wm[..c], 1, c);
            matmul(g_heads_v, wm_h, &mut pass.g_a1, i + 1 < blocks.len());
            let mut g_head = vec![0.0f32; 2 * c];
            matmul(
                g_heads_v.t(),
                View::new(&pass.a1, n, c),
                &mut g_head[..c],
                false,
            );
            let gb_head = [g_heads.iter().sum::<f32>(), 0.0];
            let head_terms = (&g_head[..], &[0.0, 0.0][..], &gb_head[..]);
            block
                .head
                .weight_gradients(&pass.mh, w, head_terms, &mut grads);

            // conv1
            let (gd1, gb1) = block
                .conv1
                .output_backward(&pass.m1, p, &pass.y1, &mut pass.g_a1);
            let g_y1 = View::new(&pass.g_a1, n, c);
            let mut g1 = vec![0.0f32; c * c];
            matmul(g_y1.t(), View::new(&pass.a0, n, c), &mut g1, false);
            matmul(g_y1, View::new(&pass.m1.wm, c, c), &mut pass.g_a0, false);
            block
                .conv1
                .weight_gradients(&pass.m1, w, (&g1, &gd1, &gb1), &mut grads);

            // conv0: the Fourier part, then the previous block's features (upsampled)
            let (gd0, gb0) = block
                .conv0
                .output_backward(&pass.m0, p, &pass.y0, &mut pass.g_a0);
            let g_y0 = View::new(&pass.g_a0, n, c);
            let mut g0 = vec![0.0f32; c * d_in];
            let mut g_pe = vec![0.0f32; c * two_f];
            matmul(
                g_y0.t(),
                View::new(&block.basis, n, two_f),
                &mut g_pe,
                false,
            );
            if let Some(prev) = below.last_mut() {
                let (hp, wp) = blocks[i - 1].size;
                let g_yx = upsample2x_adjoint(&pass.g_a0, (hp, wp), c);
                let g_yx_v = View::new(&g_yx, hp * wp, c);
                let mut g_x = vec![0.0f32; c * c_x];
                matmul(
                    g_yx_v.t(),
                    View::new(&prev.a1, hp * wp, c_x),
                    &mut g_x,
                    false,
                );
                let wm_x = View::columns(&pass.m0.wm, c, d_in, 0, c_x);
                matmul(g_yx_v, wm_x, &mut prev.g_a1, false);
                for (row, x) in g0.chunks_exact_mut(d_in).zip(g_x.chunks_exact(c_x)) {
                    row[..c_x].copy_from_slice(x);
                }
                g_heads = upsample2x_adjoint(&g_heads, (hp, wp), 1);
            }
            for (row, pe) in g0.chunks_exact_mut(d_in).zip(g_pe.chunks_exact(two_f)) {
                row[c_x..].copy_from_slice(pe);
            }
            block
                .conv0
                .weight_gradients(&pass.m0, w, (&g0, &gd0, &gb0), &mut grads);
        }
        grads
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::decode::invert::invert;
    use crate::model::generator::{GeneratorConfig, MappingConfig};
    use crate::model::layers::{self, kitti_like_grid};
    use crate::util::rng::Rng;

    #[test]
    fn runs_are_the_stretches_of_true_flags() {
        let f = |s: &str| s.chars().map(|c| c == '1').collect::<Vec<_>>();
        assert_eq!(runs(&f("0110111001")), vec![1..3, 4..7, 9..10]);
        assert_eq!(runs(&f("11")), vec![0..2]);
        assert!(runs(&f("000")).is_empty());
    }

    /// A tuning stopped after some steps and taken up again ends where one straight run does.
    #[test]
    fn a_tuning_taken_up_again_ends_where_a_straight_run_ends() {
        let dev = Device::flex();
        let g = GeneratorConfig::new()
            .with_mapping(MappingConfig::new().with_d_z(8).with_d_w(8))
            .with_channels(vec![12, 8])
            .with_n_freq(vec![5, 4])
            .with_lh(vec![3, 4])
            .with_lw(vec![2, 3])
            .with_seed(3)
            .init(&dev);
        let cache = g.prepare(&kitti_like_grid(4, 16), &dev);
        let target: Vec<f32> = (0..64).map(|k| 0.3 * (k as f32 * 0.4).sin()).collect();
        let mask: Vec<f32> = (0..64).map(|k| f32::from(u8::from(k % 5 != 2))).collect();
        let w0: Vec<f32> = (0..8).map(|i| 0.2 * (i as f32).cos()).collect();
        let schedule = Schedule {
            tune_steps: 6,
            ..Schedule::fast()
        };
        let straight = Tuning::new(&g, &cache, &target, &mask, w0.clone(), &schedule).finish(&g);
        let mut tuning = Tuning::new(&g, &cache, &target, &mask, w0, &schedule);
        tuning.run_to(2);
        let handed = tuning.weights(&g);
        assert_eq!(tuning.steps(), 2);
        let resumed = tuning.finish(&g);
        assert_eq!(straight.losses, resumed.losses);
        let flat = |g: &Generator| tensor_to_vec(g.blocks[1].conv1.weight.val());
        assert_eq!(flat(&straight.generator), flat(&resumed.generator));
        assert_ne!(flat(&handed), flat(&resumed.generator));
        assert_ne!(flat(&handed), flat(&g));
    }

    #[test]
    fn upsampling_matches_the_generator_and_its_adjoint_is_the_transpose() {
        let (h, w, c) = (3, 4, 2);
        let x: Vec<f32> = (0..h * w * c).map(|i| (i as f32 * 0.9).sin()).collect();
        let dev = Device::flex();
        let want = tensor_to_vec(layers::upsample2x(tensor_from(
            x.clone(),
            [1, h, w, c],
            &dev,
        )));
        let got = upsample2x(&x, (h, w), c);
        for (g, e) in got.iter().zip(&want) {
            assert!((g - e).abs() < 1e-6, "{g} vs {e}");
        }
        // <up(x), g> = <x, up^T(g)>
        let g: Vec<f32> = (0..got.len()).map(|i| (i as f32 * 0.37).cos()).collect();
        let lhs: f32 = got.iter().zip(&g).map(|(a, b)| a * b).sum();
        let back = upsample2x_adjoint(&g, (h, w), c);
        let rhs: f32 = x.iter().zip(&back).map(|(a, b)| a * b).sum();
        assert!((lhs - rhs).abs() < 1e-4, "{lhs} vs {rhs}");
    }

    /// A three-level generator small enough for exact comparisons (d_w 8).
    fn three_block_generator(seed: u64, dev: &Device) -> Generator {
        GeneratorConfig::new()
            .with_mapping(MappingConfig::new().with_d_z(8).with_d_w(8))
            .with_channels(vec![12, 8, 6])
            .with_n_freq(vec![5, 4, 3])
            .with_lh(vec![3, 4, 5])
            .with_lw(vec![2, 3, 4])
            .with_seed(seed)
            .init(dev)
    }

    /// The hand-written rendering is the generator's own, both heads, on a grid wider than
    /// any the tests tune on.
    #[test]
    fn hand_written_rendering_matches_the_generator() {
        let dev = Device::flex();
        let g = three_block_generator(7, &dev);
        let cache = g.prepare(&kitti_like_grid(8, 128), &dev);
        let w = g.mapping.forward(Rng::new(4).normal_tensor([1, 8], &dev));
        let want = g.render(w.clone(), &cache, None);
        let w = tensor_to_vec(w);
        let (x_d, keep_logit) = render(&g, &cache, &w).unwrap();
        assert_eq!(render_x_d(&g, &cache, &w).unwrap(), x_d, "x_d alone");
        for (got, want) in [(x_d, want.x_d), (keep_logit, want.keep_logit)] {
            let want = tensor_to_vec(want);
            assert_eq!(got.len(), 8 * 128);
            assert_eq!(got.len(), want.len());
            let scale = want.iter().fold(0.0f32, |m, v| m.max(v.abs()));
            let worst = (got.iter().zip(&want))
                .map(|(a, b)| (a - b).abs())
                .fold(0.0f32, f32::max);
            assert!(
                scale > 1e-3 && worst < 1e-5 * scale.max(1.0),
                "{worst} of {scale}"
            );
        }
    }

    /// Both paths from the same start: the losses of every step and the tuned rendering agree.
    #[test]
    fn hand_written_tuning_matches_autodiff() {
        let dev = Device::flex();
        let ad = dev.clone().autodiff();
        let g = three_block_generator(5, &dev);
        let grid = kitti_like_grid(8, 32);
        let cache = g.prepare(&grid, &dev);
        let cache_ad = g.prepare(&grid, &ad);
        let mut rng = Rng::new(9);
        let w_true = g.mapping.forward(rng.normal_tensor([1, 8], &dev));
        let target = tensor_to_vec(g.render(w_true, &cache, None).x_d);
        // Holes, so that the masked pooling is exercised.
        let mask: Vec<f32> = (0..target.len())
            .map(|k| f32::from(u8::from(k % 7 != 3 && k % 11 != 5)))
            .collect();
        let w0: Vec<f32> = (0..8).map(|i| 0.3 * (i as f32).sin()).collect();
        let schedule = Schedule {
            tune_steps: 8,
            tune_lr: 1e-2,
            ..Schedule::fast()
        };
        assert!(supports(&g, &schedule));
        let hand = Tuning::new(&g, &cache_ad, &target, &mask, w0.clone(), &schedule).finish(&g);
        let auto = invert(
            &g,
            &cache_ad,
            tensor_from(target.clone(), [1, 1, 8, 32], &ad),
            tensor_from(mask, [1, 1, 8, 32], &ad),
            w0.clone(),
            &schedule,
            &ad,
        );
        assert!(hand.losses[7] < 0.8 * hand.losses[0], "{:?}", hand.losses);
        for (a, b) in hand.losses.iter().zip(&auto.losses) {
            assert!((a - b).abs() < 1e-4 * b.abs().max(1.0), "{a} vs {b}");
        }
        let w_t = tensor_from(w0, [1, 8], &dev);
        let render = |g: &Generator| tensor_to_vec(g.render(w_t.clone(), &cache, None).x_d);
        let (x_hand, x_auto) = (render(&hand.generator), render(&auto.generator));
        let worst = (x_hand.iter().zip(&x_auto))
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        assert!(worst < 1e-4, "tuned renderings differ by {worst}");
        // The shared generator is untouched.
        let untouched = render(&g);
        assert!(untouched.iter().zip(&x_hand).any(|(a, b)| a != b));
        // Heads and biases stay as trained; the synthesis weights move.
        for tuned in [&hand.generator, &auto.generator] {
            for (b, t) in g.blocks.iter().zip(&tuned.blocks) {
                let same1 = |a: &Param<Tensor<1>>, b: &Param<Tensor<1>>| {
                    tensor_to_vec(a.val()) == tensor_to_vec(b.val())
                };
                let same2 = |a: &Param<Tensor<2>>, b: &Param<Tensor<2>>| {
                    tensor_to_vec(a.val()) == tensor_to_vec(b.val())
                };
                assert!(same2(&b.head.weight, &t.head.weight) && same1(&b.head.bias, &t.head.bias));
                assert!(same2(&b.head.affine.weight, &t.head.affine.weight));
                assert!(same1(&b.conv0.bias, &t.conv0.bias) && same1(&b.conv1.bias, &t.conv1.bias));
                assert!(!same2(&b.conv1.weight, &t.conv1.weight));
                assert!(!same2(&b.conv0.affine.weight, &t.conv0.affine.weight));
            }
        }
    }
}
