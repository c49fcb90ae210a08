//! The DUSty v2 implicit generator: mapping network z -> w (with the w_avg tracker), synthesis
//! blocks of per-pixel modulated layers fed with circular Fourier features of a per-pixel angle
//! pyramid, and skip heads for inverse depth (tanh) and the ray-drop logit. Also the subgrid
//! (random azimuth phase) rendering used in training.
//!
//! The generator is a function of the angles, not of a pixel grid: any grid whose size is
//! divisible by 2^(blocks - 1) can be rendered, e.g. a 2x denser one, without retraining. The
//! optional local path (a 3x3 convolution in the finest blocks) is the exception: it sees
//! neighbouring pixels, so it is tied to the pixel spacing it was trained at.

use std::f32::consts::TAU;
use std::sync::{Arc, OnceLock};

use burn::config::Config;
use burn::module::{Module, Param};
use burn::tensor::{Device, Tensor};

use super::conv::{LocalConv, LocalConvConfig};
use super::layers::{
    AngleGridExt, EqualLinear, EqualLinearConfig, FourierFeatures, FourierFeaturesConfig,
    ModulatedLinear, ModulatedLinearConfig, fixed_param, upsample2x,
};
use crate::lidar::AngleGrid;
use crate::util::rng::Rng;
use crate::util::tensor::{tensor_from, tensor_to_vec};

// ---------------------------------------------------------------------------------------------
// Mapping network
// ---------------------------------------------------------------------------------------------

/// Mapping network (paper / reference section 2): PixelNorm then `n_layers` equalised-lr
/// linear layers with lr multiplier 0.01.
#[derive(Config, Debug)]
pub struct MappingConfig {
    #[config(default = 512)]
    pub d_z: usize,
    #[config(default = 512)]
    pub d_w: usize,
    #[config(default = 2)]
    pub n_layers: usize,
    #[config(default = 0.01)]
    pub lr_mul: f32,
    /// EMA decay of the tracked mean latent w_avg.
    #[config(default = 0.995)]
    pub w_avg_beta: f32,
}

#[derive(Module, Debug)]
pub struct Mapping {
    pub layers: Vec<EqualLinear>,
    /// `[d_w]` running mean of w (non-trainable; truncation and inversion start point).
    pub w_avg: Param<Tensor<1>>,
    #[module(skip)]
    pub w_avg_beta: f32,
}

impl MappingConfig {
    pub fn init(&self, rng: &mut Rng, device: &Device) -> Mapping {
        let layers = (0..self.n_layers)
            .map(|i| {
                let d_in = if i == 0 { self.d_z } else { self.d_w };
                EqualLinearConfig::new(d_in, self.d_w)
                    .with_lr_mul(self.lr_mul)
                    .with_activate(true)
                    .init(rng, device)
            })
            .collect();
        Mapping {
            layers,
            w_avg: fixed_param(Tensor::zeros([self.d_w], device)),
            w_avg_beta: self.w_avg_beta,
        }
    }
}

impl Mapping {
    /// # Shapes
    /// - z: `[batch, d_z]` -> w: `[batch, d_w]`
    pub fn forward(&self, z: Tensor<2>) -> Tensor<2> {
        let norm = z.clone().powi_scalar(2).mean_dim(1).add_scalar(1e-8).sqrt(); // [batch, 1]
        let mut w = z / norm; // [batch, d_z] pixel norm
        for layer in &self.layers {
            w = layer.forward(w); // [batch, d_w]
        }
        w
    }

    /// Move w_avg towards the batch mean of `w` (training only; no gradient).
    pub fn track_w_avg(mut self, w: &Tensor<2>) -> Self {
        let mean = w.clone().detach().inner().mean_dim(0).squeeze_dim::<1>(0); // [d_w]
        let beta = self.w_avg_beta;
        self.w_avg = self.w_avg.map(|avg| {
            let device = avg.device();
            let avg_inner = avg.inner();
            let new = mean.clone() + (avg_inner - mean).mul_scalar(beta);
            let new = if device.is_autodiff() {
                new.autodiff()
            } else {
                new
            };
            new.set_require_grad(false)
        });
        self
    }

    /// Truncation trick: w_avg + psi (w - w_avg).
    pub fn truncate(&self, w: Tensor<2>, psi: f32) -> Tensor<2> {
        let avg = self.w_avg.val().unsqueeze_dim::<2>(0); // [1, d_w]
        avg.clone() + (w - avg).mul_scalar(psi)
    }
}

// ---------------------------------------------------------------------------------------------
// Synthesis block
// ---------------------------------------------------------------------------------------------

/// One synthesis block: [upsampled features, Fourier(angles)] -> 2 modulated layers -> heads.
#[derive(Config, Debug)]
pub struct SynthesisBlockConfig {
    /// Channels coming from the previous block (0 for the first).
    pub d_prev: usize,
    pub d_out: usize,
    pub d_w: usize,
    pub fourier: FourierFeaturesConfig,
    /// Add the local 3x3 path after the block's second layer.
    #[config(default = false)]
    pub local: bool,
}

#[derive(Module, Debug)]
pub struct SynthesisBlock {
    pub fourier: FourierFeatures,
    pub conv0: ModulatedLinear,
    pub conv1: ModulatedLinear,
    /// The local path, in the blocks that have one.
    pub local: Option<LocalConv>,
    /// Two channels, no demodulation: inverse depth and ray-drop logit.
    pub head: ModulatedLinear,
}

impl SynthesisBlockConfig {
    pub fn init(&self, rng: &mut Rng, device: &Device) -> SynthesisBlock {
        let fourier = self.fourier.init(rng, device);
        let d_in = self.d_prev + 2 * self.fourier.n_freq;
        SynthesisBlock {
            fourier,
            conv0: ModulatedLinearConfig::new(d_in, self.d_out, self.d_w).init(rng, device),
            conv1: ModulatedLinearConfig::new(self.d_out, self.d_out, self.d_w).init(rng, device),
            local: self
                .local
                .then(|| LocalConvConfig::new(self.d_out, self.d_w).init(rng, device)),
            head: ModulatedLinearConfig::new(self.d_out, 2, self.d_w)
                .with_demodulate(false)
                .with_activate(false)
                .init(rng, device),
        }
    }
}

/// The Fourier basis of one pyramid level.
#[derive(Debug, Clone)]
pub struct LevelBasis {
    pub height: usize,
    pub width: usize,
    /// `[H*W, 2F]`
    pub basis: Tensor<2>,
}

/// Everything the generator needs from an angle grid, computed once per grid: the Fourier
/// basis of each pyramid level. Never rebuild it inside an optimisation loop.
#[derive(Debug, Clone)]
pub struct GridCache {
    pub height: usize,
    pub width: usize,
    pub levels: Vec<LevelBasis>,
    /// The levels' bases as host floats, copied out once for the passes written by hand
    /// ([`GridCache::host_bases`]).
    host: Arc<OnceLock<Vec<Arc<[f32]>>>>,
}

impl GridCache {
    fn new(height: usize, width: usize, levels: Vec<LevelBasis>) -> GridCache {
        GridCache {
            height,
            width,
            levels,
            host: Arc::default(),
        }
    }

    /// Each level's basis (`[H*W, 2F]`, row-major) on the host, copied on first use and
    /// shared by every clone of this cache.
    pub fn host_bases(&self) -> &[Arc<[f32]>] {
        self.host.get_or_init(|| {
            (self.levels.iter())
                .map(|level| tensor_to_vec(level.basis.clone()).into())
                .collect()
        })
    }

    /// The cache cut to its first `columns` columns: a window of the turn whose every level
    /// keeps its share of the full grid's own angles (a pyramid built on the window alone
    /// would average its edges with the other end). `columns` must divide by the coarsest
    /// level's factor.
    pub fn first_columns(&self, columns: usize) -> GridCache {
        let levels = (self.levels.iter())
            .map(|level| {
                let factor = self.width / level.width;
                assert!(
                    columns.is_multiple_of(factor) && columns <= self.width,
                    "a window of {columns} columns does not fit the pyramid's factor {factor}"
                );
                let (h, w, wk) = (level.height, level.width, columns / factor);
                let f2 = level.basis.dims()[1];
                LevelBasis {
                    height: h,
                    width: wk,
                    basis: (level.basis.clone().reshape([h, w, f2]))
                        .narrow(1, 0, wk)
                        .reshape([h * wk, f2]),
                }
            })
            .collect();
        GridCache::new(self.height, columns, levels)
    }

    /// The cache cut to its first `blocks` levels: the generator renders with those blocks
    /// alone, at the finest kept level's resolution (the low-pass part of the full image).
    pub fn first_blocks(&self, blocks: usize) -> GridCache {
        let levels = self.levels[..blocks.clamp(1, self.levels.len())].to_vec();
        let finest = levels.last().expect("a grid has at least one level");
        GridCache::new(finest.height, finest.width, levels)
    }
}

// ---------------------------------------------------------------------------------------------
// Generator
// ---------------------------------------------------------------------------------------------

/// DUSty v2 generator (reference section 2). Defaults are the paper's: 5 blocks at 4x32 ...
/// 64x512 with 512/256/128/64/32 channels, 256 Fourier pairs per block, (Lh, Lw) = (5,4) ...
/// (9,8), 4.37 M parameters.
#[derive(Config, Debug)]
pub struct GeneratorConfig {
    #[config(default = "MappingConfig::new()")]
    pub mapping: MappingConfig,
    /// Channels per block, coarsest first.
    #[config(default = "vec![512, 256, 128, 64, 32]")]
    pub channels: Vec<usize>,
    /// Fourier frequency pairs per block.
    #[config(default = "vec![256, 256, 256, 256, 256]")]
    pub n_freq: Vec<usize>,
    /// log2 elevation bandwidth per block.
    #[config(default = "vec![5, 6, 7, 8, 9]")]
    pub lh: Vec<u32>,
    /// log2 azimuth bandwidth per block (integer frequencies).
    #[config(default = "vec![4, 5, 6, 7, 8]")]
    pub lw: Vec<u32>,
    /// How many of the finest blocks have the local 3x3 path (0: the paper's generator).
    #[config(default = 0)]
    pub local_blocks: usize,
    /// Scale of the summed head outputs before tanh.
    #[config(default = 0.25)]
    pub output_gain: f32,
    /// Seed of the initial weights and Fourier frequencies.
    #[config(default = 0)]
    pub seed: u64,
}

#[derive(Module, Debug)]
pub struct Generator {
    pub mapping: Mapping,
    pub blocks: Vec<SynthesisBlock>,
    #[module(skip)]
    pub output_gain: f32,
}

/// Generator output in network units.
#[derive(Debug, Clone)]
pub struct GeneratorOutput {
    /// `[batch, 1, H, W]` inverse depth 2 x_d - 1 in [-1, 1] (before ray drop).
    pub x_d: Tensor<4>,
    /// `[batch, 1, H, W]` ray-drop logit: sigmoid(logit) is the KEEP probability.
    pub keep_logit: Tensor<4>,
}

impl GeneratorConfig {
    /// Grid sizes must divide by this (`Generator::resolution_step`).
    pub fn resolution_step(&self) -> usize {
        1 << self.channels.len().saturating_sub(1)
    }

    /// Refuses sizes that cannot be built or would not fit in memory.
    pub fn check(&self) -> anyhow::Result<()> {
        use crate::util::bounds;
        let blocks = self.channels.len();
        bounds::sizes("generator.channels", &self.channels, 1..=8, 1..=4096)?;
        bounds::sizes("generator.n_freq", &self.n_freq, blocks..=blocks, 1..=4096)?;
        let lh: Vec<usize> = self.lh.iter().map(|&v| v as usize).collect();
        let lw: Vec<usize> = self.lw.iter().map(|&v| v as usize).collect();
        bounds::sizes("generator.lh", &lh, blocks..=blocks, 0..=20)?;
        bounds::sizes("generator.lw", &lw, blocks..=blocks, 0..=20)?;
        bounds::size("generator.local_blocks", self.local_blocks, 0..=blocks)?;
        bounds::size("generator.mapping.d_z", self.mapping.d_z, 1..=4096)?;
        bounds::size("generator.mapping.d_w", self.mapping.d_w, 1..=4096)?;
        bounds::size("generator.mapping.n_layers", self.mapping.n_layers, 1..=32)
    }

    /// The CPU configuration chosen by measurement (docs/model_benchmarks.md).
    pub fn cpu() -> Self {
        Self::new()
            .with_mapping(MappingConfig::new().with_d_z(128).with_d_w(128))
            .with_channels(vec![128, 64, 32, 16, 16])
            .with_n_freq(vec![64, 64, 32, 32, 16])
    }

    /// Multiply-accumulates per image of `height x width` (modulated layers, heads, mapping;
    /// the style affines and elementwise work are negligible), as the model is defined.
    /// `forward_fourier` multiplies the previous block's features before upsampling them, so
    /// the executed count is lower (1.28 instead of 1.48 GMAC at the reference size).
    pub fn macs_per_image(&self, height: usize, width: usize) -> u64 {
        let n = self.channels.len();
        let mut macs = (self.mapping.d_z * self.mapping.d_w
            + (self.mapping.n_layers.saturating_sub(1)) * self.mapping.d_w * self.mapping.d_w)
            as u64;
        for i in 0..n {
            let k = 1usize << (n - 1 - i);
            let pixels = ((height / k) * (width / k)) as u64;
            let d_prev = if i == 0 { 0 } else { self.channels[i - 1] };
            let c = self.channels[i];
            let d_in = d_prev + 2 * self.n_freq[i];
            let local = if self.has_local(i) { 9 * c * c } else { 0 };
            macs += pixels * (d_in * c + c * c + local + 2 * c) as u64;
        }
        macs
    }

    /// Whether block `i` (coarsest first) has the local path.
    fn has_local(&self, i: usize) -> bool {
        i + self.local_blocks >= self.channels.len()
    }

    pub fn init(&self, device: &Device) -> Generator {
        assert!(
            !self.channels.is_empty()
                && self.channels.len() == self.n_freq.len()
                && self.channels.len() == self.lh.len()
                && self.channels.len() == self.lw.len(),
            "generator config: channels, n_freq, lh and lw need one entry per block"
        );
        let mut rng = Rng::new(self.seed);
        let mapping = self.mapping.init(&mut rng, device);
        let blocks = (0..self.channels.len())
            .map(|i| {
                let d_prev = if i == 0 { 0 } else { self.channels[i - 1] };
                let fourier =
                    FourierFeaturesConfig::new(self.lh[i], self.lw[i]).with_n_freq(self.n_freq[i]);
                SynthesisBlockConfig::new(d_prev, self.channels[i], self.mapping.d_w, fourier)
                    .with_local(self.has_local(i))
                    .init(&mut rng, device)
            })
            .collect();
        Generator {
            mapping,
            blocks,
            output_gain: self.output_gain,
        }
    }
}

impl Generator {
    /// This generator's weights with `fresh`'s local paths where it has none. A new path
    /// starts as the identity, so the result draws exactly what this generator draws: a
    /// trained generator gains the path and goes on training.
    pub fn with_local_paths_of(self, fresh: Generator) -> Generator {
        let blocks = self
            .blocks
            .into_iter()
            .zip(fresh.blocks)
            .map(|(block, new)| SynthesisBlock {
                local: block.local.or(new.local),
                ..block
            })
            .collect();
        Generator { blocks, ..self }
    }

    pub fn d_z(&self) -> usize {
        self.mapping
            .layers
            .first()
            .map(|l| l.weight.dims()[1])
            .unwrap_or(0)
    }

    pub fn d_w(&self) -> usize {
        self.mapping.w_avg.dims()[0]
    }

    /// Grid sizes must divide by this.
    pub fn resolution_step(&self) -> usize {
        1 << (self.blocks.len() - 1)
    }

    /// Compute the per-level Fourier bases of an angle grid (once per grid).
    pub fn prepare(&self, angles: &AngleGrid, device: &Device) -> GridCache {
        let step = self.resolution_step();
        assert!(
            angles.height.is_multiple_of(step) && angles.width.is_multiple_of(step),
            "grid {}x{} must be divisible by {step}",
            angles.height,
            angles.width
        );
        let levels = angles
            .pyramid(self.blocks.len())
            .iter()
            .zip(&self.blocks)
            .map(|(grid, block)| LevelBasis {
                height: grid.height,
                width: grid.width,
                basis: block.fourier.basis(grid, device),
            })
            .collect();
        GridCache::new(angles.height, angles.width, levels)
    }

    /// Synthesis from w. `azimuth_shift` (fractions of a turn, one per sample) adds a phase
    /// 2 pi s to every azimuth before encoding.
    ///
    /// # Shapes
    /// - w: `[batch, d_w]` -> raw heads `[batch, 2, H, W]` (x_d pre-tanh, keep logit)
    pub fn synthesis(
        &self,
        w: Tensor<2>,
        grid: &GridCache,
        azimuth_shift: Option<Tensor<1>>,
    ) -> Tensor<4> {
        let b = w.dims()[0];
        let mut x: Option<Tensor<4>> = None; // [batch, h, w, ch]
        let mut heads: Option<Tensor<4>> = None; // [batch, h, w, 2]
        for (block, level) in self.blocks.iter().zip(&grid.levels) {
            let (h, wd) = (level.height, level.width);
            let rotation = azimuth_shift.clone().map(|s| block.fourier.rotation(s));
            // x is at the previous level; conv0 upsamples it (after its product, see there).
            let y = block.conv0.forward_fourier(
                x,
                true,
                level.basis.clone(),
                rotation.as_ref(),
                w.clone(),
            ); // [batch, h*w, ch]
            let y = block.conv1.forward(y, w.clone()); // [batch, h*w, ch]
            let y = match &block.local {
                Some(local) => local.forward(y, h, wd, w.clone()), // [batch, h*w, ch]
                None => y,
            };
            let head = block
                .head
                .forward(y.clone(), w.clone())
                .reshape([b, h, wd, 2]); // [batch, h, w, 2]
            heads = Some(match heads {
                Some(prev) => upsample2x(prev) + head,
                None => head,
            });
            let c = y.dims()[2];
            x = Some(y.reshape([b, h, wd, c]));
        }
        let heads = heads.expect("generator has at least one block"); // [batch, H, W, 2]
        heads.permute([0, 3, 1, 2]).mul_scalar(self.output_gain) // [batch, 2, H, W]
    }

    /// Render from latents z on `grid`.
    ///
    /// # Shapes
    /// - z: `[batch, d_z]` -> x_d, keep_logit: `[batch, 1, H, W]`
    pub fn forward(&self, z: Tensor<2>, grid: &GridCache) -> GeneratorOutput {
        let w = self.mapping.forward(z); // [batch, d_w]
        self.render(w, grid, None)
    }

    /// Render from w, optionally with subgrid training: the azimuths get a per-sample phase
    /// 2 pi s and the image is shifted back by s W columns (circular, bilinear), so the pixels
    /// sample the scene between the grid columns while the image stays aligned.
    pub fn render(
        &self,
        w: Tensor<2>,
        grid: &GridCache,
        subgrid_shift: Option<&[f32]>,
    ) -> GeneratorOutput {
        let device = w.device();
        let raw = match subgrid_shift {
            Some(shift) => {
                let b = shift.len();
                let s = tensor_from(shift.to_vec(), [b], &device);
                let raw = self.synthesis(w, grid, Some(s)); // [batch, 2, H, W]
                // Azimuth decreases with the column index (pi - (j + 0.5) 2pi / W), so adding
                // 2 pi s shows, at column j, what belongs at column j - sW: read it from j + sW.
                let px: Vec<f32> = shift.iter().map(|s| -s * grid.width as f32).collect();
                shift_columns(raw, &px)
            }
            None => self.synthesis(w, grid, None),
        };
        let x_d = raw.clone().narrow(1, 0, 1).tanh(); // [batch, 1, H, W]
        let keep_logit = raw.narrow(1, 1, 1); // [batch, 1, H, W]
        GeneratorOutput { x_d, keep_logit }
    }
}

impl Generator {
    /// Columns rendered beyond each side of a window and cut off: the upsampling between
    /// levels and the subgrid interpolation wrap around the rendered strip, and what wraps
    /// reaches about one coarsest column plus one column of each finer level inwards.
    pub fn window_margin(&self) -> usize {
        2 * self.resolution_step()
    }

    /// Windows of the turn, rendered alone: sample `i` shows the full grid's columns
    /// `start[i]..start[i] + W` (circular) seen at subgrid phase `phase[i]` (fractions of a
    /// column, as [`Generator::render`] does for the whole turn). `grid` is the full grid's
    /// cache cut to `W + 2 margin` columns ([`GridCache::first_columns`]) and `full_width`
    /// the turn's columns.
    ///
    /// # Shapes
    /// - w: `[batch, d_w]` -> x_d, keep_logit: `[batch, 1, H, W]`
    pub fn render_window(
        &self,
        w: Tensor<2>,
        grid: &GridCache,
        full_width: usize,
        start: &[usize],
        phase: &[f32],
    ) -> GeneratorOutput {
        let device = w.device();
        let b = start.len();
        assert_eq!(b, phase.len(), "one phase per window");
        let margin = self.window_margin();
        let window = grid.width - 2 * margin;
        // Column j of the strip shows the full grid's column j - s W at azimuth phase 2 pi s
        // (see `render`); s places strip column 0 at start - margin + phase.
        let turns: Vec<f32> = (start.iter().zip(phase))
            .map(|(&c, &f)| -((c as f32 - margin as f32) + f) / full_width as f32)
            .collect();
        let raw = self.synthesis(w, grid, Some(tensor_from(turns, [b], &device)));
        let raw = shift_columns(raw, phase).narrow(3, margin, window); // [batch, 2, H, W]
        let x_d = raw.clone().narrow(1, 0, 1).tanh();
        let keep_logit = raw.narrow(1, 1, 1);
        GeneratorOutput { x_d, keep_logit }
    }
}

/// Per-sample circular shift along W with linear interpolation: `out[.., j] = x[.., j - p_b]`
/// (fractional p). One batched matmul with host-built `[W, W]` interpolation matrices.
///
/// # Shapes
/// - x: `[batch, ch, H, W]` -> `[batch, ch, H, W]`
pub fn shift_columns(x: Tensor<4>, shift_px: &[f32]) -> Tensor<4> {
    let [b, c, h, w] = x.dims();
    assert_eq!(b, shift_px.len(), "one shift per sample");
    let mut m = vec![0f32; b * w * w];
    for (i, p) in shift_px.iter().enumerate() {
        let p = p.rem_euclid(w as f32);
        let k0 = p.floor();
        let t = p - k0;
        let k0 = k0 as usize;
        // out[j] = (1 - t) x[j - k0] + t x[j - k0 - 1]; M[src, j] so that out = x M.
        for j in 0..w {
            let src0 = (j + w - k0 % w) % w;
            let src1 = (src0 + w - 1) % w;
            m[i * w * w + src0 * w + j] += 1.0 - t;
            m[i * w * w + src1 * w + j] += t;
        }
    }
    let m = tensor_from(m, [b, w, w], &x.device()); // [batch, W, W]
    let y = x.reshape([b, c * h, w]).matmul(m); // [batch, ch*H, W]
    y.reshape([b, c, h, w])
}

/// Random subgrid phases s ~ U(0, 1), one per sample.
pub fn random_subgrid_shift(rng: &mut Rng, batch: usize) -> Vec<f32> {
    (0..batch).map(|_| rng.uniform()).collect()
}

/// Azimuth offset in radians of a subgrid phase.
pub fn subgrid_offset_rad(s: f32) -> f32 {
    s * TAU
}

#[cfg(test)]
mod tests {
    use super::super::layers::{kitti_like_grid, roll};
    use super::*;
    use crate::util::tensor::tensor_to_vec;
    use burn::module::ModuleVisitor;

    fn tiny(blocks: usize) -> GeneratorConfig {
        GeneratorConfig::new()
            .with_mapping(MappingConfig::new().with_d_z(8).with_d_w(8))
            .with_channels(vec![8; blocks])
            .with_n_freq(vec![4; blocks])
            .with_lh((0..blocks as u32).map(|i| 3 + i).collect())
            .with_lw((0..blocks as u32).map(|i| 2 + i).collect())
            .with_seed(5)
    }

    fn max_abs(x: Tensor<4>) -> f32 {
        x.abs().max().into_scalar::<f32>()
    }

    #[test]
    fn one_column_azimuth_shift_shifts_output_by_one_column() {
        // Single-level model: every column of the grid is a column of the finest level.
        let dev = Device::flex();
        let g = tiny(1).init(&dev);
        let z = Rng::new(1).normal_tensor([2, 8], &dev);
        let grid = kitti_like_grid(4, 16);
        let a = g.forward(z.clone(), &g.prepare(&grid, &dev));
        let b = g.forward(z, &g.prepare(&grid.roll_columns(1), &dev));
        let diff = max_abs(roll(a.x_d.clone(), 1, 3) - b.x_d.clone());
        assert!(diff < 1e-5, "x_d diff {diff}");
        let diff = max_abs(roll(a.keep_logit, 1, 3) - b.keep_logit);
        assert!(diff < 1e-5, "logit diff {diff}");
        // And the roll is not trivially satisfied by a constant image.
        assert!(max_abs(roll(a.x_d.clone(), 1, 3) - a.x_d) > 1e-4);
    }

    #[test]
    fn a_window_shows_the_columns_of_the_whole_turn() {
        let dev = Device::flex();
        let g = tiny(3).init(&dev);
        let w = g.mapping.forward(Rng::new(3).normal_tensor([3, 8], &dev));
        let grid = kitti_like_grid(8, 64);
        let full = g.prepare(&grid, &dev);
        let whole = g.render(w.clone(), &full, None).x_d; // [3, 1, 8, 64]
        let window = 16;
        let strip = full.first_columns(window + 2 * g.window_margin());
        // Starts on a coarsest column (4 here) render the very same pixels, across the seam too.
        let start = [0, 12, 56];
        let out = g
            .render_window(w.clone(), &strip, 64, &start, &[0.0; 3])
            .x_d;
        for (i, &c) in start.iter().enumerate() {
            let expected =
                roll(whole.clone().narrow(0, i, 1), -(c as isize), 3).narrow(3, 0, window);
            let diff = max_abs(out.clone().narrow(0, i, 1) - expected);
            assert!(diff < 1e-4, "window at column {c}: {diff}");
        }
        // Between coarsest columns the pyramid samples other angles: close, not the same.
        let between = g.render_window(w, &strip, 64, &[2, 2, 2], &[0.0; 3]).x_d;
        let expected = roll(whole.narrow(0, 0, 1), -2, 3).narrow(3, 0, window);
        let diff = max_abs(between.narrow(0, 0, 1) - expected);
        assert!(diff > 1e-5 && diff < 0.5, "off-coarse start: {diff}");
    }

    #[test]
    fn coarse_column_shift_is_exact_for_the_whole_pyramid() {
        // Three levels: a shift by one coarsest-level column (4 full-res columns) rolls every
        // level by a whole number of its own columns, so the output rolls exactly.
        let dev = Device::flex();
        let g = tiny(3).init(&dev);
        let z = Rng::new(2).normal_tensor([2, 8], &dev);
        let grid = kitti_like_grid(8, 32);
        let a = g.forward(z.clone(), &g.prepare(&grid, &dev));
        let b = g.forward(z, &g.prepare(&grid.roll_columns(4), &dev));
        let diff = max_abs(roll(a.x_d, 4, 3) - b.x_d);
        assert!(diff < 1e-5, "diff {diff}");
    }

    #[test]
    fn subgrid_shift_by_whole_coarse_columns_is_identity() {
        // Phase s = 4/W moves the scene by 4 columns; shifting back must give the plain render.
        let dev = Device::flex();
        let g = tiny(3).init(&dev);
        let mut rng = Rng::new(3);
        let w = g.mapping.forward(rng.normal_tensor([2, 8], &dev));
        let grid = g.prepare(&kitti_like_grid(8, 32), &dev);
        let plain = g.render(w.clone(), &grid, None);
        let shifted = g.render(w, &grid, Some(&[4.0 / 32.0, 8.0 / 32.0]));
        let diff = max_abs(plain.x_d - shifted.x_d);
        assert!(diff < 1e-4, "diff {diff}");
    }

    #[test]
    fn renders_a_denser_grid_without_retraining() {
        let dev = Device::flex();
        let g = tiny(3).init(&dev);
        let z = Rng::new(4).normal_tensor([1, 8], &dev);
        let grid = kitti_like_grid(16, 64);
        let base = g.forward(z.clone(), &g.prepare(&grid, &dev)).x_d;
        let dense = g.forward(z, &g.prepare(&grid.resample(32, 128), &dev)).x_d;
        assert_eq!(dense.dims(), [1, 1, 32, 128]);
        // The dense render samples the same continuous function: 2x2 means match the base.
        let pooled = dense
            .reshape([1, 16, 2, 64, 2])
            .mean_dim(4)
            .mean_dim(2)
            .reshape([1, 1, 16, 64]);
        let a = tensor_to_vec(base);
        let p = tensor_to_vec(pooled);
        let corr = correlation(&a, &p);
        assert!(corr > 0.9, "correlation {corr}");
    }

    fn correlation(a: &[f32], b: &[f32]) -> f32 {
        let n = a.len() as f32;
        let (ma, mb) = (a.iter().sum::<f32>() / n, b.iter().sum::<f32>() / n);
        let cov: f32 = a.iter().zip(b).map(|(x, y)| (x - ma) * (y - mb)).sum();
        let va: f32 = a.iter().map(|x| (x - ma).powi(2)).sum();
        let vb: f32 = b.iter().map(|y| (y - mb).powi(2)).sum();
        cov / (va * vb).sqrt()
    }

    #[test]
    fn a_generator_gains_local_paths_without_changing_what_it_draws() {
        let dev = Device::flex();
        let base = tiny(3).init(&dev);
        let grown = base
            .clone()
            .with_local_paths_of(tiny(3).with_local_blocks(2).init(&dev));
        let has_local: Vec<bool> = grown.blocks.iter().map(|b| b.local.is_some()).collect();
        assert_eq!(has_local, [false, true, true]);
        let z = Rng::new(7).normal_tensor([2, 8], &dev);
        let grid = kitti_like_grid(8, 32);
        let a = base.forward(z.clone(), &base.prepare(&grid, &dev));
        let b = grown.forward(z, &grown.prepare(&grid, &dev));
        assert_eq!(tensor_to_vec(a.x_d), tensor_to_vec(b.x_d));
        assert_eq!(tensor_to_vec(a.keep_logit), tensor_to_vec(b.keep_logit));
    }

    #[test]
    fn save_then_load_gives_identical_outputs() {
        let dev = Device::flex();
        let g = tiny(2).init(&dev);
        // Change w_avg so that the fixed params are non-trivial.
        let g = g
            .clone()
            .with_mapping_w_avg(Rng::new(9).normal_tensor([8], &dev));
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("g.bpk");
        g.clone().save_file(&path).expect("save");
        let other = tiny(2).with_seed(77).init(&dev);
        let loaded = other.try_load_file(&path).expect("load");
        let z = Rng::new(5).normal_tensor([2, 8], &dev);
        let grid = kitti_like_grid(4, 16);
        let a = g.forward(z.clone(), &g.prepare(&grid, &dev));
        let b = loaded.forward(z, &loaded.prepare(&grid, &dev));
        assert_eq!(tensor_to_vec(a.x_d), tensor_to_vec(b.x_d));
        assert_eq!(tensor_to_vec(a.keep_logit), tensor_to_vec(b.keep_logit));
        assert_eq!(
            tensor_to_vec(g.mapping.w_avg.val()),
            tensor_to_vec(loaded.mapping.w_avg.val())
        );
    }

    impl Generator {
        fn with_mapping_w_avg(mut self, avg: Tensor<1>) -> Self {
            self.mapping.w_avg = fixed_param(avg);
            self
        }
    }

    struct GradCheck<'a> {
        grads: &'a burn::tensor::Gradients,
        trainable: usize,
        missing: Vec<String>,
        fixed_with_grad: usize,
        path: Vec<String>,
    }

    impl ModuleVisitor for GradCheck<'_> {
        fn enter_module(&mut self, name: &str, _: &str) {
            self.path.push(name.to_string());
        }
        fn exit_module(&mut self, _: &str, _: &str) {
            self.path.pop();
        }
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            let t = param.val();
            if t.is_require_grad() {
                self.trainable += 1;
                let ok = t
                    .grad(self.grads)
                    .map(|g| g.abs().sum().into_scalar::<f32>() > 0.0)
                    .unwrap_or(false);
                if !ok {
                    self.missing.push(self.path.join("."));
                }
            } else if t.grad(self.grads).is_some() {
                self.fixed_with_grad += 1;
            }
        }
    }

    #[test]
    fn gradients_reach_w_and_every_weight() {
        let dev = Device::flex().autodiff();
        let g = tiny(3).init(&dev);
        let mut rng = Rng::new(6);
        let w = rng.normal_tensor([2, 8], &dev).require_grad();
        let grid = g.prepare(&kitti_like_grid(8, 32), &dev);
        let out = g.render(w.clone(), &grid, Some(&[0.1, 0.6]));
        let loss = (out.x_d * rng.normal_tensor([2, 1, 8, 32], &dev)).sum()
            + (out.keep_logit * rng.normal_tensor([2, 1, 8, 32], &dev)).sum();
        let grads = loss.backward();
        let gw = w.grad(&grads).expect("gradient w.r.t. w");
        assert!(gw.abs().sum().into_scalar::<f32>() > 0.0);
        let mut check = GradCheck {
            grads: &grads,
            trainable: 0,
            missing: vec![],
            fixed_with_grad: 0,
            path: vec![],
        };
        g.visit(&mut check);
        // The mapping is not on the path from w; everything in the synthesis must be.
        let missing: Vec<_> = check
            .missing
            .iter()
            .filter(|p| !p.starts_with("mapping"))
            .collect();
        assert!(missing.is_empty(), "no gradient for {missing:?}");
        assert!(check.trainable > 10);
        assert_eq!(check.fixed_with_grad, 0, "fixed params must not train");
        // And through z the mapping gets gradients too.
        let z = rng.normal_tensor([2, 8], &dev);
        let out = g.forward(z, &grid);
        let grads = out.x_d.sum().backward();
        let mut check = GradCheck {
            grads: &grads,
            trainable: 0,
            missing: vec![],
            fixed_with_grad: 0,
            path: vec![],
        };
        g.visit(&mut check);
        assert!(
            check.missing.is_empty(),
            "no gradient from z for {:?}",
            check.missing
        );
    }

    #[test]
    fn w_avg_tracks_and_truncation_pulls_towards_it() {
        let dev = Device::flex();
        let g = tiny(1).init(&dev);
        let w = Tensor::<2>::ones([4, 8], &dev);
        let mapping = g.mapping.track_w_avg(&w);
        let avg = tensor_to_vec(mapping.w_avg.val());
        assert!(avg.iter().all(|v| (v - 0.005).abs() < 1e-6), "{avg:?}");
        let t = tensor_to_vec(mapping.truncate(w, 0.0));
        assert!(t.iter().all(|v| (v - 0.005).abs() < 1e-6));
    }
}
