//! The encoder for inference, on host slices: the same function as
//! [`Encoder`](super::encoder::Encoder), with each convolution as one matrix product per block
//! of pixels over their 3 x 3 neighbourhoods (im2col), single-threaded
//! ([`crate::util::matmul`]). Activations are channels-last, so a pixel's neighbourhood is a
//! few contiguous runs; decoding then needs no tensor library and runs one scan per thread.

use super::encoder::{Conv3, Encoder, SLOPE};
use crate::util::matmul::{View, matmul};
use crate::util::tensor::tensor_to_vec;

/// Output pixels per matrix product: bounds the neighbourhood buffer to a few megabytes.
const BLOCK: usize = 2048;

/// An activation map, channels-last: element (row, col, channel) at `(row * w + col) * c + ch`.
struct Map {
    h: usize,
    w: usize,
    c: usize,
    data: Vec<f32>,
}

/// A convolution's weights as one matrix `[(ky, kx, c_in), c_out]` and its bias.
#[derive(Debug, Clone)]
struct HostConv {
    kernel: (usize, usize),
    c_in: usize,
    c_out: usize,
    /// Column step between kernel taps (azimuth dilation).
    dilation: usize,
    weight: Vec<f32>,
    bias: Vec<f32>,
}

impl HostConv {
    fn from_conv(conv: &burn::nn::conv::Conv2d, dilation: usize) -> Self {
        let [c_out, c_in, kh, kw] = conv.weight.dims();
        let w = tensor_to_vec(conv.weight.val());
        let mut weight = vec![0.0f32; kh * kw * c_in * c_out];
        for co in 0..c_out {
            for ci in 0..c_in {
                for ky in 0..kh {
                    for kx in 0..kw {
                        let src = ((co * c_in + ci) * kh + ky) * kw + kx;
                        weight[((ky * kw + kx) * c_in + ci) * c_out + co] = w[src];
                    }
                }
            }
        }
        let bias = conv
            .bias
            .as_ref()
            .map(|b| tensor_to_vec(b.val()))
            .unwrap_or_else(|| vec![0.0; c_out]);
        HostConv {
            kernel: (kh, kw),
            c_in,
            c_out,
            dilation,
            weight,
            bias,
        }
    }

    fn from_conv3(conv: &Conv3) -> Self {
        Self::from_conv(&conv.conv, conv.dilation)
    }

    /// A 3 x 3 convolution, same size: zero rows above and below, columns wrapping around
    /// the turn when `circular`, else zero.
    fn same(&self, x: &Map, circular: bool) -> Map {
        let (h, w) = (x.h, x.w);
        let reach = self.dilation as isize;
        self.apply(x, h, w, |i, j, ky, kx| {
            let r = i as isize + ky as isize - 1;
            let c = j as isize + (kx as isize - 1) * reach;
            if r < 0 || r >= h as isize {
                return None;
            }
            let c = if circular && (reach as usize) <= w {
                c.rem_euclid(w as isize)
            } else if c < 0 || c >= w as isize {
                return None;
            } else {
                c
            };
            Some(r as usize * w + c as usize)
        })
    }

    /// A convolution with stride equal to its kernel (the 2 x 2 patch embedding).
    fn patches(&self, x: &Map) -> Map {
        let (kh, kw) = self.kernel;
        let w = x.w;
        self.apply(x, x.h / kh, x.w / kw, |i, j, ky, kx| {
            Some((i * kh + ky) * w + j * kw + kx)
        })
    }

    /// The convolution whose tap (ky, kx) at output pixel (i, j) reads input pixel
    /// `source(i, j, ky, kx)` (`None`: zero padding).
    fn apply(
        &self,
        x: &Map,
        h: usize,
        w: usize,
        source: impl Fn(usize, usize, usize, usize) -> Option<usize>,
    ) -> Map {
        let (kh, kw) = self.kernel;
        let (ci, co) = (self.c_in, self.c_out);
        debug_assert_eq!(x.c, ci);
        let taps = kh * kw * ci;
        let n = h * w;
        let mut out = vec![0.0f32; n * co];
        let mut cols = vec![0.0f32; BLOCK.min(n) * taps];
        for start in (0..n).step_by(BLOCK) {
            let m = BLOCK.min(n - start);
            let cols = &mut cols[..m * taps];
            for (p, patch) in cols.chunks_exact_mut(taps).enumerate() {
                let (i, j) = ((start + p) / w, (start + p) % w);
                for ky in 0..kh {
                    for kx in 0..kw {
                        let dst = &mut patch[(ky * kw + kx) * ci..][..ci];
                        match source(i, j, ky, kx) {
                            Some(q) => dst.copy_from_slice(&x.data[q * ci..(q + 1) * ci]),
                            None => dst.fill(0.0),
                        }
                    }
                }
            }
            let block = &mut out[start * co..(start + m) * co];
            for row in block.chunks_exact_mut(co) {
                row.copy_from_slice(&self.bias);
            }
            matmul(
                View::new(cols, m, taps),
                View::new(&self.weight, taps, co),
                block,
                true,
            );
        }
        Map {
            h,
            w,
            c: co,
            data: out,
        }
    }
}

fn leaky(mut x: Map) -> Map {
    let s = SLOPE as f32;
    x.data.iter_mut().for_each(|v| {
        if *v < 0.0 {
            *v *= s
        }
    });
    x
}

/// `a + b`, elementwise.
fn add(mut a: Map, b: &Map) -> Map {
    a.data.iter_mut().zip(&b.data).for_each(|(x, y)| *x += y);
    a
}

/// 2 x 2 average pooling.
fn pool2(x: &Map) -> Map {
    let (h, w, c) = (x.h / 2, x.w / 2, x.c);
    let mut data = vec![0.0f32; h * w * c];
    for i in 0..h {
        for j in 0..w {
            let dst = &mut data[(i * w + j) * c..][..c];
            for (di, dj) in [(0, 0), (0, 1), (1, 0), (1, 1)] {
                let q = (2 * i + di) * x.w + 2 * j + dj;
                dst.iter_mut()
                    .zip(&x.data[q * c..(q + 1) * c])
                    .for_each(|(d, v)| *d += 0.25 * v);
            }
        }
    }
    Map { h, w, c, data }
}

/// `coarse` upsampled twice (nearest), its channels followed by those of `fine`.
fn up_and_concat(coarse: &Map, fine: &Map) -> Map {
    let (h, w) = (fine.h, fine.w);
    let c = coarse.c + fine.c;
    let mut data = Vec::with_capacity(h * w * c);
    for i in 0..h {
        for j in 0..w {
            let q = (i / 2) * coarse.w + j / 2;
            data.extend_from_slice(&coarse.data[q * coarse.c..(q + 1) * coarse.c]);
            data.extend_from_slice(&fine.data[(i * w + j) * fine.c..][..fine.c]);
        }
    }
    Map { h, w, c, data }
}

/// The encoder's weights, arranged for [`HostEncoder::forward`].
#[derive(Debug, Clone)]
pub struct HostEncoder {
    stem: HostConv,
    half: Vec<HostConv>,
    down_quarter: HostConv,
    quarter: HostConv,
    down_eighth: HostConv,
    eighth: Vec<HostConv>,
    up_quarter: HostConv,
    up_half: HostConv,
    out: HostConv,
}

impl HostEncoder {
    pub fn from_net(e: &Encoder) -> Self {
        HostEncoder {
            stem: HostConv::from_conv(&e.stem, 1),
            half: e.half.iter().map(HostConv::from_conv3).collect(),
            down_quarter: HostConv::from_conv3(&e.down_quarter),
            quarter: HostConv::from_conv3(&e.quarter),
            down_eighth: HostConv::from_conv3(&e.down_eighth),
            eighth: e.eighth.iter().map(HostConv::from_conv3).collect(),
            up_quarter: HostConv::from_conv3(&e.up_quarter),
            up_half: HostConv::from_conv3(&e.up_half),
            out: HostConv::from_conv(&e.out, 1),
        }
    }

    /// The latent grid of one encoder input (channels-first `[INPUT_CHANNELS, H, W]`, as
    /// [`super::encoder_input`] gives it), channels-first `[latent, H/2, W/2]`.
    pub fn forward(&self, input: &[f32], [h, w]: [usize; 2], circular: bool) -> Vec<f32> {
        let c = input.len() / (h * w).max(1);
        let mut x = Map {
            h,
            w,
            c,
            data: vec![0.0; input.len()],
        };
        for ch in 0..c {
            for p in 0..h * w {
                x.data[p * c + ch] = input[ch * h * w + p];
            }
        }
        let mut half = leaky(self.stem.patches(&x));
        for conv in &self.half {
            let y = leaky(conv.same(&half, circular));
            half = add(half, &y);
        }
        let q = leaky(self.down_quarter.same(&pool2(&half), circular));
        let quarter = add(leaky(self.quarter.same(&q, circular)), &q);
        let mut e = leaky(self.down_eighth.same(&pool2(&quarter), circular));
        for conv in &self.eighth {
            let y = leaky(conv.same(&e, circular));
            e = add(e, &y);
        }
        let q = leaky(self.up_quarter.same(&up_and_concat(&e, &quarter), circular));
        let h2 = leaky(self.up_half.same(&up_and_concat(&q, &half), circular));
        let out = self.out.patches(&h2);
        let (n, c) = (out.h * out.w, out.c);
        let mut first = vec![0.0f32; n * c];
        for p in 0..n {
            for ch in 0..c {
                first[ch * n + p] = out.data[p * c + ch];
            }
        }
        first
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::spatial::{EncoderConfig, INPUT_CHANNELS};
    use crate::util::rng::Rng;
    use crate::util::tensor::tensor_from;
    use burn::tensor::Device;

    #[test]
    fn the_host_encoder_encodes_what_the_network_encodes() {
        let device = Device::flex();
        let mut rng = Rng::new(5);
        let enc = EncoderConfig::new().init(&mut rng, &device);
        let host = HostEncoder::from_net(&enc);
        let (h, w) = (16, 48);
        let x = rng.normal_vec(INPUT_CHANNELS * h * w);
        for circular in [true, false] {
            let t = tensor_from(x.clone(), [1, INPUT_CHANNELS, h, w], &device);
            let want = tensor_to_vec(enc.forward(t, circular));
            let got = host.forward(&x, [h, w], circular);
            assert_eq!(want.len(), got.len());
            for (a, b) in want.iter().zip(&got) {
                assert!(
                    (a - b).abs() < 1e-4 * (1.0 + a.abs()),
                    "{a} vs {b} ({circular})"
                );
            }
        }
    }
}
