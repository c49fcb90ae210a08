//! DUSty v2 inverted into a spatial latent: one model for every sensor.
//!
//! The global-latent generator renders a whole scan from one vector w, so it must store every
//! object of every scan in its weights. Here an [`encoder`] maps the observed scan, on the
//! sensor's own grid, to a latent grid at half its resolution, which stands in for the
//! generator's coarse features; the implicit [`render`]er (DUSty v2's finer levels: Fourier
//! features of each query's own angles, per-query layers) turns that grid into inverse depth
//! x_d and the ray-drop probability x_n at any (elevation, azimuth). The structure of a decoded
//! scan thus comes from the scan, and the network only learns how LiDAR scenes look locally.
//!
//! Observations distinguish three states per ray: a return (its range), a known drop (the
//! sensor fired and nothing came back) and unknown (held back, or a beam the sensor lacks). The
//! drop probability of a ray is rendered from an observation in which that ray is unknown
//! ([`decode`]), so x_n predicts whether the ray returns instead of copying whether it did.

pub mod decode;
pub mod encoder;
pub mod host;
pub mod host_encoder;
pub mod prior;
pub mod render;

use std::path::Path;

use anyhow::{Context, Result};
use burn::config::Config;
use burn::module::Module;
use burn::store::ModuleRecord;
use burn::tensor::{Bytes, Device, Tensor};

pub use encoder::{EncoderConfig, INPUT_CHANNELS, MULTIPLE};
pub use render::{Queries, Query, Rendered, RendererConfig};

use crate::lidar::AngleGrid;
use crate::util::rng::Rng;
use crate::util::tensor::tensor_from;

/// The file name of a spatial model's weights in its folder (beside `config.json`).
pub const WEIGHTS: &str = "spatial.bpk";

#[derive(Config, Debug, PartialEq)]
pub struct SpatialConfig {
    /// Always "spatial": tells this model's `config.json` from a generator's.
    #[config(default = "String::from(\"spatial\")")]
    pub family: String,
    #[config(default = "EncoderConfig::new()")]
    pub encoder: EncoderConfig,
    #[config(default = "RendererConfig::new()")]
    pub renderer: RendererConfig,
    /// Returns nearer than this or farther than `max_range_m` are treated as no return.
    #[config(default = 0.3)]
    pub min_range_m: f32,
    #[config(default = 250.0)]
    pub max_range_m: f32,
    /// Weight of x_n against the scan's own per-beam drop rates in `raydrop_prob`
    /// ([`decode::blend_with_row_rates`]); chosen on the validation recordings.
    #[config(default = 1.0)]
    pub x_n_weight: f32,
}

#[derive(Module, Debug)]
pub struct SpatialNet {
    pub encoder: encoder::Encoder,
    pub renderer: render::Renderer,
}

impl SpatialConfig {
    pub fn init(&self, rng: &mut Rng, device: &Device) -> SpatialNet {
        SpatialNet {
            encoder: self.encoder.init(rng, device),
            renderer: self.renderer.init(self.encoder.latent, rng, device),
        }
    }

    /// A new network whose head is random rather than zero, for tests that must see through
    /// it (a new model's zero head renders its prior and one half everywhere).
    #[cfg(test)]
    pub(crate) fn init_for_test(&self, rng: &mut Rng, device: &Device) -> SpatialNet {
        let net = self.init(rng, device);
        SpatialNet {
            renderer: net.renderer.with_random_head(rng, device),
            ..net
        }
    }

    /// A config from its JSON; settings it predates take their defaults.
    fn from_json(saved: serde_json::Value) -> Result<Self> {
        let mut value = serde_json::to_value(SpatialConfig::new())?;
        crate::util::json::merge(&mut value, saved);
        Ok(serde_json::from_value(value)?)
    }

    /// Reads a model folder's `config.json`.
    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("failed to read '{}'", path.display()))?;
        let value: serde_json::Value = serde_json::from_str(&text)
            .with_context(|| format!("'{}' is not JSON", path.display()))?;
        anyhow::ensure!(
            value["family"] == "spatial",
            "'{}' is not a spatial model's config (a generator's folder? decode with it by adding \
             --decoder gan)",
            path.display()
        );
        let config = SpatialConfig::from_json(value)
            .with_context(|| format!("'{}' is not a spatial model config", path.display()))?;
        anyhow::ensure!(
            config.family == "spatial",
            "'{}' is a '{}' model, not a spatial one",
            path.display(),
            config.family
        );
        Ok(config)
    }
}

/// What is known of each ray of a scan on its grid.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Ray {
    Return(f32),
    Dropped,
    Unknown,
}

/// An observed scan on its sensor's grid: one [`Ray`] per pixel, row-major, the grid, and
/// whether the grid is a whole turn (its rows wrap around).
#[derive(Debug, Clone)]
pub struct Observation<'a> {
    pub rays: &'a [Ray],
    pub angles: &'a AngleGrid,
    pub circular: bool,
}

/// Values per ray that describe what was observed of it: normalised log range of a return,
/// "returned", "known" (all 0 for an unknown ray).
pub const RAY_FEATURES: usize = 3;

/// Values per ray the model is shown: its [`ray_features`], then its [`prior::prior`].
pub const OWN_FEATURES: usize = RAY_FEATURES + prior::PRIOR_FEATURES;

// The encoder reads each ray's own features and its angles (elevation, sin and cos azimuth).
const _: () = assert!(INPUT_CHANNELS == OWN_FEATURES + 3);

/// What was observed of one ray, as the encoder's first channels and the renderer's own-ray
/// input see it.
pub fn ray_features(ray: Ray, config: &SpatialConfig) -> [f32; RAY_FEATURES] {
    match ray {
        Ray::Return(r) if r >= config.min_range_m && r <= config.max_range_m => {
            [prior::normalised_log(r), 1.0, 1.0]
        }
        Ray::Return(_) | Ray::Dropped => [0.0, 0.0, 1.0],
        Ray::Unknown => [0.0; RAY_FEATURES],
    }
}

/// What the model is shown of every ray of an observation, `[H W, OWN_FEATURES]` row-major.
pub fn own_features(obs: &Observation, config: &SpatialConfig) -> Vec<f32> {
    let prior = prior::prior(obs.rays, obs.angles, obs.circular, config);
    obs.rays
        .iter()
        .zip(prior.chunks_exact(prior::PRIOR_FEATURES))
        .flat_map(|(&ray, p)| {
            ray_features(ray, config)
                .into_iter()
                .chain(p.iter().copied())
        })
        .collect()
}

/// The log depth each ray's rendering corrects ([`prior::base_log_depth`]), from its own
/// features.
pub fn base_log_depths(own: &[f32]) -> Vec<f32> {
    own.chunks_exact(OWN_FEATURES)
        .map(|f| prior::base_log_depth(&f[RAY_FEATURES..]))
        .collect()
}

/// The encoder input of one observation from its [`own_features`], `[INPUT_CHANNELS, H', W']`
/// with H' and W' rounded up to [`MULTIPLE`]; padding is unknown. Channels: the own features,
/// elevation, sin and cos of azimuth.
pub fn encoder_input(own: &[f32], angles: &AngleGrid) -> (Vec<f32>, [usize; 2]) {
    let (h, w) = (angles.height, angles.width);
    let (hp, wp) = (h.next_multiple_of(MULTIPLE), w.next_multiple_of(MULTIPLE));
    let plane = hp * wp;
    let mut x = vec![0.0f32; INPUT_CHANNELS * plane];
    for i in 0..h {
        for j in 0..w {
            let k = i * w + j;
            let p = i * wp + j;
            for (c, &v) in own[k * OWN_FEATURES..(k + 1) * OWN_FEATURES]
                .iter()
                .enumerate()
            {
                x[c * plane + p] = v;
            }
            let (s, c) = angles.azimuth_rad[k].sin_cos();
            x[OWN_FEATURES * plane + p] = 2.0 * angles.elevation_rad[k];
            x[(OWN_FEATURES + 1) * plane + p] = s;
            x[(OWN_FEATURES + 2) * plane + p] = c;
        }
    }
    (x, [hp, wp])
}

/// The queries of every pixel of `angles` (the grid the encoder saw), in row-major order.
pub fn grid_queries(angles: &AngleGrid) -> Vec<Query> {
    let mut q = Vec::with_capacity(angles.len());
    for i in 0..angles.height {
        for j in 0..angles.width {
            let k = i * angles.width + j;
            q.push(Query {
                row: pixel_to_cell(i as f32),
                col: pixel_to_cell(j as f32),
                elevation: angles.elevation_rad[k],
                azimuth: angles.azimuth_rad[k],
            });
        }
    }
    q
}

/// A pixel coordinate of the input grid as a latent-cell coordinate (cells are 2x2 pixels;
/// both count from the centre of the first).
pub fn pixel_to_cell(p: f32) -> f32 {
    (p + 0.5) / 2.0 - 0.5
}

impl SpatialNet {
    /// Latent grids of a batch of encoder inputs, `[batch, INPUT_CHANNELS, H', W']` (host,
    /// row-major) -> `[batch, latent, H'/2, W'/2]`.
    pub fn encode(
        &self,
        inputs: Vec<f32>,
        batch: usize,
        [hp, wp]: [usize; 2],
        circular: bool,
        device: &Device,
    ) -> Tensor<4> {
        let x = tensor_from(inputs, [batch, INPUT_CHANNELS, hp, wp], device);
        self.encoder.forward(x, circular)
    }

    pub fn render(
        &self,
        latent: Tensor<4>,
        queries: &Queries,
        own: Tensor<3>,
        base: Tensor<2>,
    ) -> Rendered {
        self.renderer.forward(latent, queries, own, base)
    }
}

/// The shipped model's config and weights, compiled into the binary.
const SHIPPED_CONFIG: &str = include_str!("../../../models/spatial/config.json");
const SHIPPED_WEIGHTS: &[u8] = include_bytes!("../../../models/spatial/spatial.bpk");

/// A trained spatial model: its config and network.
#[derive(Debug, Clone)]
pub struct SpatialModel {
    pub config: SpatialConfig,
    pub net: SpatialNet,
    /// Where it came from, for reports ("shipped" or a path).
    pub source: String,
}

impl SpatialModel {
    /// The model prepared for decoding on the host ([`decode::HostModel`]).
    pub fn host(&self) -> decode::HostModel {
        decode::HostModel::new(&self.net, &self.config)
    }

    /// Loads `DIR/config.json` and `DIR/spatial.bpk`.
    pub fn load(dir: &Path, device: &Device) -> Result<Self> {
        let config = SpatialConfig::load(&dir.join("config.json"))?;
        let path = dir.join(WEIGHTS);
        let net = config
            .init(&mut Rng::new(0), device)
            .try_load_file(&path)
            .map_err(|e| anyhow::anyhow!("failed to load '{}': {e}", path.display()))?;
        Ok(SpatialModel {
            config,
            net,
            source: dir.display().to_string(),
        })
    }

    /// The weights shipped in `models/spatial`.
    pub fn shipped(device: &Device) -> Result<Self> {
        let config = serde_json::from_str(SHIPPED_CONFIG)
            .map_err(anyhow::Error::from)
            .and_then(SpatialConfig::from_json)
            .context("the shipped spatial model's config.json")?;
        let record = ModuleRecord::from_bytes(Bytes::from_bytes_vec(SHIPPED_WEIGHTS.to_vec()))
            .map_err(|e| anyhow::anyhow!("the shipped spatial weights are unreadable: {e}"))?;
        let net = config
            .init(&mut Rng::new(0), device)
            .try_load_record(record)
            .map_err(|e| {
                anyhow::anyhow!("the shipped spatial weights do not fit their config: {e}")
            })?;
        Ok(SpatialModel {
            config,
            net,
            source: "shipped".into(),
        })
    }
}
