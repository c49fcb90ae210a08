//! The renderer of the spatial-latent model: a local implicit function that turns the latent
//! grid into inverse depth and the ray-drop logit at any (elevation, azimuth).
//!
//! A query reads the four latent cells around its position on the grid, each through its own
//! linear map and weighted bilinearly, adds a linear map of its offset inside the cell and of
//! circular Fourier features of its own angles (DUSty v2's positional encoding, exactly
//! 2pi-periodic in azimuth) and a linear map of what was observed of the query's own ray and
//! its interpolation prior ([`super::prior`]), and runs the sum through a small MLP. The log
//! depth it outputs is a bounded correction of the prior's, so a model starts at
//! interpolation. The corner maps are applied to the cells before the gather, so their cost is
//! paid per cell rather than per query.

use burn::config::Config;
use burn::module::Module;
use burn::nn::{Linear, LinearConfig};
use burn::tensor::activation::leaky_relu;
use burn::tensor::{Device, Int, Tensor, TensorData};

use crate::util::init::linear;
use crate::util::rng::Rng;
use crate::util::tensor::tensor_from;

const SLOPE: f64 = 0.2;

/// Ranges are read as `(ln r - LN_MID_DEPTH) / LOG_DEPTH_SPAN`: 0.3 m to 330 m is -1 to 1.
pub const LN_MID_DEPTH: f32 = std::f32::consts::LN_10;
pub const LOG_DEPTH_SPAN: f32 = 3.5;
/// Log depth is `base + CORRECTION_SPAN * tanh(output)`: at most a factor e^3 off the prior.
pub const CORRECTION_SPAN: f32 = 3.0;

#[derive(Config, Debug, PartialEq)]
pub struct RendererConfig {
    #[config(default = 64)]
    pub hidden: usize,
    /// Fourier frequency pairs (each gives a sine and a cosine).
    #[config(default = 16)]
    pub fourier: usize,
    /// Elevation frequencies are uniform in (-2^k, 2^k) per radian.
    #[config(default = 5)]
    pub elevation_octaves: u32,
    /// Azimuth frequencies are integers in [-2^k, 2^k] (so the encoding wraps with the turn).
    #[config(default = 3)]
    pub azimuth_octaves: u32,
    #[config(default = 7)]
    pub fourier_seed: u64,
}

impl RendererConfig {
    /// Offset inside the cell (2) and the Fourier features.
    pub fn position_features(&self) -> usize {
        2 + 2 * self.fourier
    }

    /// The fixed Fourier frequencies and phases `(b_elevation, b_azimuth, phase)`, drawn from
    /// `fourier_seed`, so the weights file need not carry them.
    pub fn frequencies(&self) -> Vec<[f32; 3]> {
        let mut rng = Rng::new(self.fourier_seed);
        let le = (1u32 << self.elevation_octaves) as f32;
        let la = 1usize << self.azimuth_octaves;
        (0..self.fourier)
            .map(|_| {
                let be = rng.range(-le, le);
                let ba = rng.below(2 * la + 1) as f32 - la as f32;
                let p = rng.range(0.0, std::f32::consts::TAU);
                [be, ba, p]
            })
            .collect()
    }

    pub fn init(&self, latent: usize, rng: &mut Rng, device: &Device) -> Renderer {
        let h = self.hidden;
        Renderer {
            corners: linear(
                LinearConfig::new(latent, 4 * h).with_bias(false),
                rng,
                device,
            ),
            position: linear(LinearConfig::new(self.position_features(), h), rng, device),
            own_ray: linear(
                LinearConfig::new(super::OWN_FEATURES, h).with_bias(false),
                rng,
                device,
            ),
            mid: linear(LinearConfig::new(h, h), rng, device),
            // Zero: an untrained model renders its prior and a drop probability of one half.
            head: LinearConfig::new(h, 2)
                .with_initializer(burn::nn::Initializer::Zeros)
                .init(device),
        }
    }
}

#[derive(Module, Debug)]
pub struct Renderer {
    corners: Linear,
    position: Linear,
    own_ray: Linear,
    mid: Linear,
    head: Linear,
}

/// Where the queries of one render fall on a latent grid: the four cells of each (flat
/// indices), their bilinear weights and the position features. Shared by every scan of a
/// batch.
#[derive(Debug, Clone)]
pub struct Queries {
    pub corners: [Tensor<1, Int>; 4],
    /// `[n, 4]`
    pub weights: Tensor<2>,
    /// `[n, position_features]`
    pub position: Tensor<2>,
    pub len: usize,
}

/// One query: its place on the latent grid (row and column, in cells, fractional) and its angles.
#[derive(Debug, Clone, Copy)]
pub struct Query {
    pub row: f32,
    pub col: f32,
    pub elevation: f32,
    pub azimuth: f32,
}

/// Queries placed on a latent grid, on the host: the four cells of each (flat indices), their
/// bilinear weights and the position features, `[n, position_features]` row-major.
pub(super) struct Placed {
    pub corners: Vec<[u32; 4]>,
    pub weights: Vec<[f32; 4]>,
    pub position: Vec<f32>,
}

/// Places `queries` on a latent grid of `rows x cols` cells; columns wrap when `circular`,
/// otherwise they are clamped like rows.
pub(super) fn place(
    queries: &[Query],
    (rows, cols): (usize, usize),
    circular: bool,
    config: &RendererConfig,
) -> Placed {
    let n = queries.len();
    let freqs = config.frequencies();
    let mut placed = Placed {
        corners: Vec::with_capacity(n),
        weights: Vec::with_capacity(n),
        position: Vec::with_capacity(n * config.position_features()),
    };
    let clamp = |i: i64, len: usize| i.clamp(0, len as i64 - 1);
    for q in queries {
        let (r0, fr) = (q.row.floor(), q.row - q.row.floor());
        let (c0, fc) = (q.col.floor(), q.col - q.col.floor());
        let rows_at = [clamp(r0 as i64, rows), clamp(r0 as i64 + 1, rows)];
        let col = |c: i64| {
            if circular {
                c.rem_euclid(cols as i64)
            } else {
                clamp(c, cols)
            }
        };
        let cols_at = [col(c0 as i64), col(c0 as i64 + 1)];
        let mut idx = [0u32; 4];
        let mut w = [0.0f32; 4];
        for (k, (a, b)) in [(0, 0), (0, 1), (1, 0), (1, 1)].into_iter().enumerate() {
            idx[k] = (rows_at[a] * cols as i64 + cols_at[b]) as u32;
            let wr = if a == 0 { 1.0 - fr } else { fr };
            let wc = if b == 0 { 1.0 - fc } else { fc };
            w[k] = wr * wc;
        }
        placed.corners.push(idx);
        placed.weights.push(w);
        placed.position.push(2.0 * fr - 1.0);
        placed.position.push(2.0 * fc - 1.0);
        for [be, ba, p] in &freqs {
            let a = be * q.elevation + ba * q.azimuth + p;
            placed.position.push(a.sin());
            placed.position.push(a.cos());
        }
    }
    placed
}

impl Queries {
    /// Places `queries` on a latent grid of `rows x cols` cells ([`place`]), as tensors.
    pub fn new(
        queries: &[Query],
        cells: (usize, usize),
        circular: bool,
        config: &RendererConfig,
        device: &Device,
    ) -> Queries {
        let n = queries.len();
        let placed = place(queries, cells, circular, config);
        let int = |k: usize| {
            let v: Vec<i64> = placed.corners.iter().map(|c| i64::from(c[k])).collect();
            Tensor::<1, Int>::from_data(TensorData::new(v, [n]), device)
        };
        Queries {
            corners: [int(0), int(1), int(2), int(3)],
            weights: tensor_from(placed.weights.concat(), [n, 4], device),
            position: tensor_from(placed.position, [n, config.position_features()], device),
            len: n,
        }
    }
}

/// The renderer's outputs at every query of every scan.
#[derive(Debug, Clone)]
pub struct Rendered {
    /// Natural log of the depth in metres, `[batch, n]`.
    pub log_depth: Tensor<2>,
    /// The keep logit: `sigmoid` is the probability that the ray returns, so the ray-drop
    /// probability is x_n = 1 - sigmoid(keep_logit). `[batch, n]`
    pub keep_logit: Tensor<2>,
}

impl Renderer {
    /// The layers (corner maps, position, own ray, middle, head), for the host renderer.
    pub(super) fn layers(&self) -> (&Linear, &Linear, &Linear, &Linear, &Linear) {
        (
            &self.corners,
            &self.position,
            &self.own_ray,
            &self.mid,
            &self.head,
        )
    }

    /// The same renderer with a random head, for tests that must see through it.
    #[cfg(test)]
    pub(crate) fn with_random_head(mut self, rng: &mut Rng, device: &Device) -> Self {
        let h = self.mid.weight.dims()[1];
        self.head = linear(LinearConfig::new(h, 2), rng, device);
        self
    }

    /// # Shapes
    /// - latent: `[batch, ch, rows, cols]`, the grid `queries` were placed on
    /// - own: `[batch, n, OWN_FEATURES]`, what each scan's encoder was shown of each query's
    ///   own ray ([`super::own_features`]; queries between the observed rays read as unknown
    ///   rays with their neighbours' prior)
    /// - base: `[batch, n]`, the log depth each query corrects ([`super::base_log_depths`])
    pub fn forward(
        &self,
        latent: Tensor<4>,
        queries: &Queries,
        own: Tensor<3>,
        base: Tensor<2>,
    ) -> Rendered {
        let [b, c, rows, cols] = latent.dims();
        let cells = latent.permute([0, 2, 3, 1]).reshape([b, rows * cols, c]);
        let projected = self.corners.forward(cells); // [b, cells, 4 * hidden]
        let hidden = projected.dims()[2] / 4;
        let n = queries.len;
        let mut h = self
            .position
            .forward(queries.position.clone())
            .reshape([1, n, hidden]);
        for (k, idx) in queries.corners.iter().enumerate() {
            let gathered = projected
                .clone()
                .narrow(2, k * hidden, hidden)
                .select(1, idx.clone());
            let w = queries.weights.clone().narrow(1, k, 1).reshape([1, n, 1]);
            h = h + gathered * w;
        }
        h = h + self.own_ray.forward(own);
        let h = leaky_relu(h, SLOPE);
        let h = leaky_relu(self.mid.forward(h), SLOPE);
        let out = self.head.forward(h); // [b, n, 2]
        let log_depth = out
            .clone()
            .narrow(2, 0, 1)
            .reshape([b, n])
            .tanh()
            .mul_scalar(CORRECTION_SPAN)
            + base;
        Rendered {
            log_depth,
            keep_logit: out.narrow(2, 1, 1).reshape([b, n]),
        }
    }
}
