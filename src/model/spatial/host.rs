//! The renderer for inference, on host slices: the same function as
//! [`Renderer`](super::render::Renderer), computed in chunks of queries that stay in cache,
//! with single-threaded matrix products ([`crate::util::matmul`]). Training renders through
//! burn's autodiff; decoding needs no gradients, and rendering every ray of a full-resolution
//! scan as whole-batch tensors spends most of its time moving activations through memory.

use super::render::{CORRECTION_SPAN, Renderer};
use super::{OWN_FEATURES, Query, RendererConfig};
use crate::util::matmul::{View, matmul};
use crate::util::tensor::tensor_to_vec;

/// Queries rendered per chunk.
const CHUNK: usize = 1024;

const SLOPE: f32 = 0.2;

/// The renderer's weights, row-major `[in, out]` as burn's linear layers hold them.
#[derive(Debug, Clone)]
pub struct HostRenderer {
    hidden: usize,
    latent: usize,
    corners: Vec<f32>,
    position_w: Vec<f32>,
    position_b: Vec<f32>,
    own_w: Vec<f32>,
    mid_w: Vec<f32>,
    mid_b: Vec<f32>,
    head_w: Vec<f32>,
    head_b: Vec<f32>,
}

/// Queries placed on a latent grid, on the host: four cells and bilinear weights each, and
/// their position features (offset in the cell, Fourier features of the angles) already
/// through the renderer's position layer, since they are the same for every scan of a grid.
#[derive(Debug, Clone)]
pub struct HostQueries {
    corners: Vec<[u32; 4]>,
    weights: Vec<[f32; 4]>,
    /// `[n, hidden]`: the position layer's output (bias included).
    positions: Vec<f32>,
}

impl HostQueries {
    pub fn new(
        queries: &[Query],
        cells: (usize, usize),
        circular: bool,
        config: &RendererConfig,
        renderer: &HostRenderer,
    ) -> Self {
        let placed = super::render::place(queries, cells, circular, config);
        let (n, f, h) = (queries.len(), config.position_features(), renderer.hidden);
        let mut positions = vec![0.0f32; n * h];
        for row in positions.chunks_exact_mut(h) {
            row.copy_from_slice(&renderer.position_b);
        }
        matmul(
            View::new(&placed.position, n, f),
            View::new(&renderer.position_w, f, h),
            &mut positions,
            true,
        );
        HostQueries {
            corners: placed.corners,
            weights: placed.weights,
            positions,
        }
    }

    pub fn len(&self) -> usize {
        self.corners.len()
    }

    pub fn is_empty(&self) -> bool {
        self.corners.is_empty()
    }
}

/// Rendered log depth and keep logit per query of one latent grid.
pub struct HostRendered {
    pub log_depth: Vec<f32>,
    pub keep_logit: Vec<f32>,
}

impl HostRenderer {
    pub fn from_net(r: &Renderer, latent: usize) -> Self {
        let (corners, position, own, mid, head) = r.layers();
        let w = |l: &burn::nn::Linear| tensor_to_vec(l.weight.val());
        let b = |l: &burn::nn::Linear| {
            l.bias
                .as_ref()
                .map(|b| tensor_to_vec(b.val()))
                .unwrap_or_default()
        };
        HostRenderer {
            hidden: mid.weight.dims()[0],
            latent,
            corners: w(corners),
            position_w: w(position),
            position_b: b(position),
            own_w: w(own),
            mid_w: w(mid),
            mid_b: b(mid),
            head_w: w(head),
            head_b: b(head),
        }
    }

    /// Renders `queries` from one latent grid, channels-first `[latent, rows, cols]` as the
    /// encoder gives it, with what was shown of each query's own ray (`[n, OWN_FEATURES]`) and
    /// the log depth it corrects (`[n]`).
    pub fn render(
        &self,
        latent: &[f32],
        queries: &HostQueries,
        own: &[f32],
        base: &[f32],
    ) -> HostRendered {
        let (h, c) = (self.hidden, self.latent);
        let cells = latent.len() / c.max(1);
        // Cell-major latent, then each cell through the four corner maps at once.
        let mut cell_major = vec![0.0f32; cells * c];
        for ch in 0..c {
            for cell in 0..cells {
                cell_major[cell * c + ch] = latent[ch * cells + cell];
            }
        }
        let mut projected = vec![0.0f32; cells * 4 * h];
        matmul(
            View::new(&cell_major, cells, c),
            View::new(&self.corners, c, 4 * h),
            &mut projected,
            false,
        );
        drop(cell_major);
        let n = queries.len();
        let mut out = HostRendered {
            log_depth: Vec::with_capacity(n),
            keep_logit: Vec::with_capacity(n),
        };
        let mut h1 = vec![0.0f32; CHUNK * h];
        let mut h2 = vec![0.0f32; CHUNK * h];
        let mut o = vec![0.0f32; CHUNK * 2];
        for start in (0..n).step_by(CHUNK) {
            let m = CHUNK.min(n - start);
            let (h1, h2, o) = (&mut h1[..m * h], &mut h2[..m * h], &mut o[..m * 2]);
            h1.copy_from_slice(&queries.positions[start * h..(start + m) * h]);
            let own = &own[start * OWN_FEATURES..(start + m) * OWN_FEATURES];
            matmul(
                View::new(own, m, OWN_FEATURES),
                View::new(&self.own_w, OWN_FEATURES, h),
                h1,
                true,
            );
            for q in 0..m {
                let row = &mut h1[q * h..(q + 1) * h];
                let (idx, wts) = (queries.corners[start + q], queries.weights[start + q]);
                for k in 0..4 {
                    let base = idx[k] as usize * 4 * h + k * h;
                    let p = &projected[base..base + h];
                    let wk = wts[k];
                    for (v, x) in row.iter_mut().zip(p) {
                        *v += wk * x;
                    }
                }
                row.iter_mut().for_each(|v| *v = leaky(*v));
            }
            matmul(View::new(h1, m, h), View::new(&self.mid_w, h, h), h2, false);
            for q in 0..m {
                let row = &mut h2[q * h..(q + 1) * h];
                for (v, b) in row.iter_mut().zip(&self.mid_b) {
                    *v = leaky(*v + b);
                }
            }
            matmul(View::new(h2, m, h), View::new(&self.head_w, h, 2), o, false);
            for q in 0..m {
                let d = (o[2 * q] + self.head_b[0]).tanh();
                out.log_depth.push(base[start + q] + CORRECTION_SPAN * d);
                out.keep_logit.push(o[2 * q + 1] + self.head_b[1]);
            }
        }
        out
    }
}

fn leaky(v: f32) -> f32 {
    if v >= 0.0 { v } else { SLOPE * v }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::spatial::{Queries, SpatialConfig};
    use crate::util::rng::Rng;
    use crate::util::tensor::tensor_from;
    use burn::tensor::Device;

    #[test]
    fn the_host_renderer_renders_what_the_network_renders() {
        let device = Device::flex();
        let config = SpatialConfig::new();
        let net = config.init_for_test(&mut Rng::new(3), &device);
        let mut rng = Rng::new(8);
        let (c, rows, cols) = (config.encoder.latent, 4, 9);
        let latent = rng.normal_vec(c * rows * cols);
        let queries: Vec<Query> = (0..2500)
            .map(|_| Query {
                row: rng.range(-0.5, rows as f32),
                col: rng.range(-1.0, cols as f32 + 1.0),
                elevation: rng.range(-0.4, 0.1),
                azimuth: rng.range(-3.1, 3.1),
            })
            .collect();
        let n = queries.len();
        let own = rng.normal_vec(n * OWN_FEATURES);
        let base = rng.normal_vec(n);
        let expected = net.render(
            tensor_from(latent.clone(), [1, c, rows, cols], &device),
            &Queries::new(&queries, (rows, cols), true, &config.renderer, &device),
            tensor_from(own.clone(), [1, n, OWN_FEATURES], &device),
            tensor_from(base.clone(), [1, n], &device),
        );
        let host = HostRenderer::from_net(&net.renderer, c);
        let placed = HostQueries::new(&queries, (rows, cols), true, &config.renderer, &host);
        let got = host.render(&latent, &placed, &own, &base);
        let close = |a: Vec<f32>, b: &[f32]| {
            a.iter()
                .zip(b)
                .all(|(x, y)| (x - y).abs() < 1e-4 * (1.0 + x.abs()))
        };
        assert!(close(tensor_to_vec(expected.log_depth), &got.log_depth));
        assert!(close(tensor_to_vec(expected.keep_logit), &got.keep_logit));
    }
}
