//! Building blocks of the DUSty v2 generator: equalised-lr linear, the per-pixel modulated
//! fully-connected layer (StyleGAN2 modulation + demodulation as matmuls), circular Fourier
//! features, the [1,3,3,1] resampling filter (circular along azimuth, replicate along elevation)
//! and the per-pixel angle grid with its pyramid.
//!
//! Feature maps in the generator are channels-last, `[batch, H*W, ch]` or `[batch, H, W, ch]`:
//! every layer is a 1x1 "conv", i.e. a matmul on the last dimension, so no permutes are needed.

use std::f32::consts::TAU;

use burn::config::Config;
use burn::module::{Module, Param};
use burn::tensor::activation::relu;
use burn::tensor::{Device, Tensor};

use crate::util::rng::Rng;

use crate::lidar::AngleGrid;
use crate::util::tensor::{tensor_from, tensor_to_vec};

/// LeakyReLU(0.2) scaled by sqrt(2) to keep unit variance (StyleGAN2).
///
/// Written as `sqrt(2) (0.2 x + 0.8 relu(x))`, the same function: under autodiff burn's
/// `leaky_relu` becomes compare + `mask_where`, and its backward two more `mask_where` passes,
/// which flex runs as a scalar, branchy, single-threaded loop (15 % of an inversion step at
/// the reference size); `relu` has its own vectorised forward and backward kernels.
pub fn lrelu_gain<const D: usize>(x: Tensor<D>) -> Tensor<D> {
    const NEG: f32 = 0.2 * std::f32::consts::SQRT_2;
    const POS_MINUS_NEG: f32 = 0.8 * std::f32::consts::SQRT_2;
    relu(x.clone()).mul_scalar(POS_MINUS_NEG) + x.mul_scalar(NEG)
}

// ---------------------------------------------------------------------------------------------
// Equalised-learning-rate linear layer
// ---------------------------------------------------------------------------------------------

/// Linear layer with equalised learning rate: weights are stored N(0, 1/lr_mul^2) and scaled at
/// run time by lr_mul / sqrt(d_input), so Adam sees the same step size for every layer.
#[derive(Config, Debug)]
pub struct EqualLinearConfig {
    pub d_input: usize,
    pub d_output: usize,
    /// Learning-rate multiplier (0.01 in the mapping network).
    #[config(default = 1.0)]
    pub lr_mul: f32,
    /// Initial bias value (1.0 for style affines so modulation starts at identity).
    #[config(default = 0.0)]
    pub bias_init: f32,
    /// Apply LeakyReLU(0.2) * sqrt(2) after the layer.
    #[config(default = false)]
    pub activate: bool,
}

#[derive(Module, Debug)]
pub struct EqualLinear {
    /// `[d_output, d_input]`
    pub weight: Param<Tensor<2>>,
    /// `[d_output]`
    pub bias: Param<Tensor<1>>,
    #[module(skip)]
    pub weight_gain: f32,
    #[module(skip)]
    pub lr_mul: f32,
    #[module(skip)]
    pub activate: bool,
}

impl EqualLinearConfig {
    pub fn init(&self, rng: &mut Rng, device: &Device) -> EqualLinear {
        let weight = rng
            .normal_tensor([self.d_output, self.d_input], device)
            .div_scalar(self.lr_mul);
        let bias =
            Tensor::<1>::ones([self.d_output], device).mul_scalar(self.bias_init / self.lr_mul);
        EqualLinear {
            weight: Param::from_tensor(weight),
            bias: Param::from_tensor(bias),
            weight_gain: self.lr_mul / (self.d_input as f32).sqrt(),
            lr_mul: self.lr_mul,
            activate: self.activate,
        }
    }
}

impl EqualLinear {
    /// # Shapes
    /// - x: `[batch, d_input]` -> `[batch, d_output]`
    pub fn forward(&self, x: Tensor<2>) -> Tensor<2> {
        let w_t = self.weight.val().mul_scalar(self.weight_gain).transpose(); // [in, out]
        let b = self
            .bias
            .val()
            .mul_scalar(self.lr_mul)
            .unsqueeze_dim::<2>(0); // [1, out]
        let y = x.matmul(w_t) + b; // [batch, out]
        if self.activate { lrelu_gain(y) } else { y }
    }
}

// ---------------------------------------------------------------------------------------------
// Modulated fully-connected layer
// ---------------------------------------------------------------------------------------------

/// Per-pixel modulated fully-connected layer (a StyleGAN2 modulated 1x1 conv).
///
/// Modulating the input instead of the weight, y = ((x * s) W^T) * d, keeps the big product a
/// single shared-weight matmul over `batch * pixels`; the demodulation coefficients
/// d = rsqrt(s^2 (W^2)^T) are one small `[batch, in] x [in, out]` matmul. No per-sample loops.
#[derive(Config, Debug)]
pub struct ModulatedLinearConfig {
    pub d_input: usize,
    pub d_output: usize,
    /// Width of the latent w.
    pub d_style: usize,
    #[config(default = true)]
    pub demodulate: bool,
    /// LeakyReLU(0.2) * sqrt(2) after bias.
    #[config(default = true)]
    pub activate: bool,
}

#[derive(Module, Debug)]
pub struct ModulatedLinear {
    /// w -> per-input-channel style s (bias initialised to 1).
    pub affine: EqualLinear,
    /// `[d_output, d_input]`, N(0,1), scaled by 1/sqrt(d_input) at run time.
    pub weight: Param<Tensor<2>>,
    /// `[d_output]`
    pub bias: Param<Tensor<1>>,
    #[module(skip)]
    pub demodulate: bool,
    #[module(skip)]
    pub activate: bool,
    #[module(skip)]
    pub weight_gain: f32,
}

impl ModulatedLinearConfig {
    pub fn init(&self, rng: &mut Rng, device: &Device) -> ModulatedLinear {
        let affine = EqualLinearConfig::new(self.d_style, self.d_input)
            .with_bias_init(1.0)
            .init(rng, device);
        ModulatedLinear {
            affine,
            weight: Param::from_tensor(rng.normal_tensor([self.d_output, self.d_input], device)),
            bias: Param::from_tensor(Tensor::zeros([self.d_output], device)),
            demodulate: self.demodulate,
            activate: self.activate,
            weight_gain: 1.0 / (self.d_input as f32).sqrt(),
        }
    }
}

/// Per-sample rotation of the Fourier phase: (cos delta, sin delta), each `[batch, n_freq]`.
#[derive(Debug, Clone)]
pub struct PhaseRotation {
    pub cos: Tensor<2>,
    pub sin: Tensor<2>,
}

impl ModulatedLinear {
    /// Plain modulated layer.
    ///
    /// # Shapes
    /// - x: `[batch, pixels, d_input]`, w: `[batch, d_style]` -> `[batch, pixels, d_output]`
    pub fn forward(&self, x: Tensor<3>, w: Tensor<2>) -> Tensor<3> {
        let [b, n, c] = x.dims();
        let s = self.affine.forward(w); // [batch, in]
        let weight = self.weight.val().mul_scalar(self.weight_gain); // [out, in]
        let x_s = x * s.clone().unsqueeze_dim::<3>(1); // [batch, pixels, in]
        let y = x_s.reshape([b * n, c]).matmul(weight.clone().transpose()); // [batch*pixels, out]
        let y = y.reshape([b, n, self.weight.dims()[0]]); // [batch, pixels, out]
        self.finish(y, s, weight)
    }

    /// First layer of a synthesis block: input = [x, sin(Fourier), cos(Fourier)], where x is
    /// the previous block's features, upsampled 2x first when `upsample` is set.
    ///
    /// The Fourier basis `[S | C]` is the same for every sample; a per-sample azimuth phase
    /// (subgrid training) only rotates each (sin, cos) pair. Folding that rotation and the style
    /// into per-sample `[2F, out]` matrices lets the encoding enter as `[S|C] @ M_b` without ever
    /// materialising the `[batch, pixels, 2F]` encoding (or computing sin/cos per step).
    ///
    /// The upsampling filter acts on each channel alike and the modulated product mixes channels
    /// per pixel, so the two commute: `up(x) s W^T = up(x s W^T)`. The x part is therefore
    /// multiplied at the previous block's resolution (4x fewer pixels) and only its `d_output`
    /// channels (half of x's in the paper's widths) are upsampled. Same function, less work.
    ///
    /// # Shapes
    /// - x: `[batch, h, w, d_input - 2F]` (`[batch, h/2, w/2, ..]` when `upsample`), or None
    ///   (first block)
    /// - basis: `[h*w, 2F]` (`[S | C]`), w: `[batch, d_style]`
    /// - rotation: per-sample (cos, sin) of the phase offsets, `[batch, F]`
    /// - -> `[batch, h*w, d_output]`
    pub fn forward_fourier(
        &self,
        x: Option<Tensor<4>>,
        upsample: bool,
        basis: Tensor<2>,
        rotation: Option<&PhaseRotation>,
        w: Tensor<2>,
    ) -> Tensor<3> {
        let [n, two_f] = basis.dims();
        let f = two_f / 2;
        let [d_out, d_in] = self.weight.dims();
        let c_x = d_in - two_f;
        let b = w.dims()[0];
        let s = self.affine.forward(w); // [batch, in]
        let weight = self.weight.val().mul_scalar(self.weight_gain); // [out, in]
        let w_t = weight.clone().transpose(); // [in, out]
        let s_s = s.clone().narrow(1, c_x, f); // [batch, F]
        let s_c = s.clone().narrow(1, c_x + f, f); // [batch, F]
        let wt_s = w_t.clone().narrow(0, c_x, f).unsqueeze_dim::<3>(0); // [1, F, out]
        let wt_c = w_t.clone().narrow(0, c_x + f, f).unsqueeze_dim::<3>(0); // [1, F, out]
        let (m_s, m_c) = match rotation {
            Some(rot) => {
                let a = (s_s.clone() * rot.cos.clone()).unsqueeze_dim::<3>(2); // [batch, F, 1]
                let bb = (s_c.clone() * rot.sin.clone()).unsqueeze_dim::<3>(2);
                let c = (s_s * rot.sin.clone()).unsqueeze_dim::<3>(2);
                let d = (s_c * rot.cos.clone()).unsqueeze_dim::<3>(2);
                let m_s = a * wt_s.clone() - bb * wt_c.clone(); // [batch, F, out]
                let m_c = c * wt_s + d * wt_c; // [batch, F, out]
                (m_s, m_c)
            }
            None => (
                s_s.unsqueeze_dim::<3>(2) * wt_s,
                s_c.unsqueeze_dim::<3>(2) * wt_c,
            ),
        };
        let m = Tensor::cat(vec![m_s, m_c], 1); // [batch, 2F, out]
        let y_pe = basis.unsqueeze_dim::<3>(0).expand([b, n, two_f]).matmul(m); // [batch, pixels, out]
        let y = match x {
            Some(x) => {
                let [_, h_x, w_x, _] = x.dims();
                let s_x = s.clone().narrow(1, 0, c_x).unsqueeze_dim::<3>(1); // [batch, 1, c_x]
                let wt_x = w_t.narrow(0, 0, c_x); // [c_x, out]
                let x = x.reshape([b, h_x * w_x, c_x]); // [batch, h_x*w_x, c_x]
                let y_x = (x * s_x).reshape([b * h_x * w_x, c_x]).matmul(wt_x); // [.., out]
                let y_x = y_x.reshape([b, h_x, w_x, d_out]);
                let y_x = if upsample { upsample2x(y_x) } else { y_x }; // [batch, h, w, out]
                let [_, h, wd, _] = y_x.dims();
                assert_eq!(h * wd, n, "x does not match the basis grid");
                y_x.reshape([b, n, d_out]) + y_pe
            }
            None => y_pe,
        };
        self.finish(y, s, weight)
    }

    /// Demodulation, bias, activation.
    fn finish(&self, y: Tensor<3>, s: Tensor<2>, weight: Tensor<2>) -> Tensor<3> {
        let y = if self.demodulate {
            let d = s
                .powi_scalar(2)
                .matmul(weight.powi_scalar(2).transpose())
                .add_scalar(1e-8)
                .sqrt()
                .recip(); // [batch, out]
            y * d.unsqueeze_dim::<3>(1)
        } else {
            y
        };
        let y = y + self.bias.val().unsqueeze_dim::<2>(0).unsqueeze_dim::<3>(0); // [batch, pixels, out]
        if self.activate { lrelu_gain(y) } else { y }
    }
}

// ---------------------------------------------------------------------------------------------
// Circular Fourier features
// ---------------------------------------------------------------------------------------------

/// Fixed random Fourier features of the (elevation, azimuth) angles, drawn once and saved with
/// the weights. Azimuth frequencies are integers, so the encoding is exactly 2pi-periodic.
#[derive(Config, Debug)]
pub struct FourierFeaturesConfig {
    /// Number of frequency pairs F (the encoding has 2F channels).
    #[config(default = 256)]
    pub n_freq: usize,
    /// log2 bandwidth along elevation: b_phi ~ U(-2^(lh-1), 2^(lh-1)).
    pub lh: u32,
    /// log2 bandwidth along azimuth: b_theta integer in [-2^(lw-1), 2^(lw-1)].
    pub lw: u32,
}

#[derive(Module, Debug)]
pub struct FourierFeatures {
    /// `[F]` elevation frequencies (non-trainable).
    pub b_phi: Param<Tensor<1>>,
    /// `[F]` integer azimuth frequencies (non-trainable).
    pub b_theta: Param<Tensor<1>>,
    /// `[F]` phases in [0, 2pi) (non-trainable).
    pub phase: Param<Tensor<1>>,
}

/// A fixed tensor that must travel with the weights but never trains.
pub fn fixed_param<const D: usize>(x: Tensor<D>) -> Param<Tensor<D>> {
    Param::from_tensor(x).set_require_grad(false)
}

impl FourierFeaturesConfig {
    pub fn init(&self, rng: &mut Rng, device: &Device) -> FourierFeatures {
        let bh = (1u64 << (self.lh - 1)) as f32;
        let bw = 1i64 << (self.lw - 1);
        let b_phi: Vec<f32> = (0..self.n_freq)
            .map(|_| (2.0 * rng.uniform() - 1.0) * bh)
            .collect();
        let b_theta: Vec<f32> = (0..self.n_freq)
            .map(|_| (rng.below((2 * bw + 1) as usize) as i64 - bw) as f32)
            .collect();
        let phase: Vec<f32> = (0..self.n_freq).map(|_| rng.uniform() * TAU).collect();
        FourierFeatures {
            b_phi: fixed_param(tensor_from(b_phi, [self.n_freq], device)),
            b_theta: fixed_param(tensor_from(b_theta, [self.n_freq], device)),
            phase: fixed_param(tensor_from(phase, [self.n_freq], device)),
        }
    }
}

impl FourierFeatures {
    pub fn n_freq(&self) -> usize {
        self.b_phi.dims()[0]
    }

    /// The basis `[S | C]` of a grid, computed on the host once per grid (sin/cos are slow in
    /// flex) in f64 so that large arguments stay exact.
    ///
    /// # Shapes
    /// -> `[H*W, 2F]`
    pub fn basis(&self, angles: &AngleGrid, device: &Device) -> Tensor<2> {
        let b_phi = tensor_to_vec(self.b_phi.val());
        let b_theta = tensor_to_vec(self.b_theta.val());
        let phase = tensor_to_vec(self.phase.val());
        let f = b_phi.len();
        let n = angles.height * angles.width;
        let mut out = vec![0f32; n * 2 * f];
        for (i, row) in out.chunks_exact_mut(2 * f).enumerate() {
            let phi = angles.elevation_rad[i] as f64;
            let theta = angles.azimuth_rad[i] as f64;
            for k in 0..f {
                let a = b_phi[k] as f64 * phi + b_theta[k] as f64 * theta + phase[k] as f64;
                row[k] = a.sin() as f32;
                row[f + k] = a.cos() as f32;
            }
        }
        tensor_from(out, [n, 2 * f], device)
    }

    /// Per-sample rotation for an azimuth offset `2 pi s_b` (subgrid training).
    ///
    /// # Shapes
    /// - shift: `[batch]` fractions of a turn -> (cos, sin) each `[batch, F]`
    pub fn rotation(&self, shift: Tensor<1>) -> PhaseRotation {
        let delta =
            shift.unsqueeze_dim::<2>(1).mul_scalar(TAU) * self.b_theta.val().unsqueeze_dim::<2>(0); // [batch, F]
        PhaseRotation {
            cos: delta.clone().cos(),
            sin: delta.sin(),
        }
    }
}

// ---------------------------------------------------------------------------------------------
// [1,3,3,1] resampling, circular along W (azimuth), replicate along H (elevation)
// ---------------------------------------------------------------------------------------------

/// Circularly shift along `dim` so that `out[i] = x[i - k]` (k may be negative).
pub fn roll<const D: usize>(x: Tensor<D>, k: isize, dim: usize) -> Tensor<D> {
    let n = x.dims()[dim] as isize;
    let k = k.rem_euclid(n) as usize;
    if k == 0 {
        return x;
    }
    let n = n as usize;
    let tail = x.clone().narrow(dim, n - k, k);
    let head = x.narrow(dim, 0, n - k);
    Tensor::cat(vec![tail, head], dim)
}

/// Shift by one with the border replicated: `out[i] = x[max(i - 1, 0)]` for k = 1,
/// `out[i] = x[min(i + 1, n - 1)]` for k = -1.
pub fn shift_replicate<const D: usize>(x: Tensor<D>, k: isize, dim: usize) -> Tensor<D> {
    let n = x.dims()[dim];
    if k > 0 {
        let first = x.clone().narrow(dim, 0, 1);
        Tensor::cat(vec![first, x.narrow(dim, 0, n - 1)], dim)
    } else {
        let last = x.clone().narrow(dim, n - 1, 1);
        Tensor::cat(vec![x.narrow(dim, 1, n - 1), last], dim)
    }
}

/// 2x upsampling with the [1,3,3,1] filter, written in its polyphase form
/// (even = x[i-1]/4 + 3x[i]/4, odd = 3x[i]/4 + x[i+1]/4): circular along W, replicate along H.
///
/// # Shapes
/// - x: `[batch, H, W, ch]` -> `[batch, 2H, 2W, ch]`
pub fn upsample2x(x: Tensor<4>) -> Tensor<4> {
    let [b, h, w, c] = x.dims();
    let prev = roll(x.clone(), 1, 2); // x[j-1]
    let next = roll(x.clone(), -1, 2); // x[j+1]
    let even = prev.mul_scalar(0.25) + x.clone().mul_scalar(0.75);
    let odd = x.mul_scalar(0.75) + next.mul_scalar(0.25);
    let x = Tensor::stack::<5>(vec![even, odd], 3).reshape([b, h, 2 * w, c]); // [batch, H, 2W, ch]
    let prev = shift_replicate(x.clone(), 1, 1);
    let next = shift_replicate(x.clone(), -1, 1);
    let even = prev.mul_scalar(0.25) + x.clone().mul_scalar(0.75);
    let odd = x.mul_scalar(0.75) + next.mul_scalar(0.25);
    Tensor::stack::<5>(vec![even, odd], 2).reshape([b, 2 * h, 2 * w, c]) // [batch, 2H, 2W, ch]
}

/// Host version of the [1,3,3,1]/8 stride-2 downsampling of one `[H, W]` plane.
fn downsample_plane(x: &[f32], h: usize, w: usize) -> Vec<f32> {
    const K: [f32; 4] = [1.0 / 8.0, 3.0 / 8.0, 3.0 / 8.0, 1.0 / 8.0];
    let (h2, w2) = (h / 2, w / 2);
    // along W (circular)
    let mut tmp = vec![0f32; h * w2];
    for r in 0..h {
        for j in 0..w2 {
            let mut acc = 0.0;
            for (t, k) in K.iter().enumerate() {
                let col = (2 * j + w + t - 1) % w;
                acc += k * x[r * w + col];
            }
            tmp[r * w2 + j] = acc;
        }
    }
    // along H (replicate)
    let mut out = vec![0f32; h2 * w2];
    for i in 0..h2 {
        for j in 0..w2 {
            let mut acc = 0.0;
            for (t, k) in K.iter().enumerate() {
                let row = (2 * i + t).saturating_sub(1).min(h - 1);
                acc += k * tmp[row * w2 + j];
            }
            out[i * w2 + j] = acc;
        }
    }
    out
}

// ---------------------------------------------------------------------------------------------
// Angle grid and pyramid
// ---------------------------------------------------------------------------------------------

/// Grid operations the generator needs: rotation, rolls, the [1,3,3,1] pyramid, resampling.
pub trait AngleGridExt {
    /// Rotate every azimuth by `offset_rad`.
    fn with_azimuth_offset(&self, offset_rad: f32) -> AngleGrid;
    /// Circularly shift the columns: `out[:, j] = self[:, j - k]`.
    fn roll_columns(&self, k: isize) -> AngleGrid;
    /// Halve the resolution: [1,3,3,1] filter on sin/cos of each angle, then atan2
    /// (azimuth circular, elevation replicated at the borders).
    fn downsample2x(&self) -> AngleGrid;
    /// Resample to `height x width` by bilinear interpolation of sin/cos (pixel centres
    /// aligned, azimuth circular, elevation clamped), then atan2. Renders denser grids.
    fn resample(&self, height: usize, width: usize) -> AngleGrid;
    /// Pyramid of `levels` grids, coarsest first, finest = `self`.
    fn pyramid(&self, levels: usize) -> Vec<AngleGrid>;
}

/// A regular grid: elevation linear from `top_rad` (row 0) to `bottom_rad` (last row),
/// azimuth of column j = pi - (j + 0.5) 2pi / W (column 0 at the rear, clockwise).
pub fn regular_grid(height: usize, width: usize, top_rad: f32, bottom_rad: f32) -> AngleGrid {
    AngleGrid::regular_columns(height, width, |r| {
        let t = if height > 1 {
            r as f32 / (height - 1) as f32
        } else {
            0.5
        };
        top_rad + t * (bottom_rad - top_rad)
    })
}

/// A regular grid spanning the KITTI HDL-64E field of view (+2.92 deg to -23.53 deg) with
/// any number of rows; the real beam table is `SensorProfile::kitti_hdl64e()`.
pub fn kitti_like_grid(height: usize, width: usize) -> AngleGrid {
    regular_grid(
        height,
        width,
        2.92f32.to_radians(),
        (-23.53f32).to_radians(),
    )
}

impl AngleGridExt for AngleGrid {
    /// Rotate every azimuth by `offset_rad`.
    fn with_azimuth_offset(&self, offset_rad: f32) -> AngleGrid {
        let mut out = self.clone();
        for a in &mut out.azimuth_rad {
            *a += offset_rad;
        }
        out
    }

    /// Circularly shift the columns: `out[:, j] = self[:, j - k]`.
    fn roll_columns(&self, k: isize) -> AngleGrid {
        let w = self.width as isize;
        let mut out = self.clone();
        for r in 0..self.height {
            for j in 0..self.width {
                let src = (j as isize - k).rem_euclid(w) as usize;
                out.elevation_rad[r * self.width + j] = self.elevation_rad[r * self.width + src];
                out.azimuth_rad[r * self.width + j] = self.azimuth_rad[r * self.width + src];
            }
        }
        out
    }

    /// Halve the resolution: [1,3,3,1] filter on sin/cos of each angle, then atan2
    /// (azimuth circular, elevation replicated at the borders).
    fn downsample2x(&self) -> AngleGrid {
        let (h, w) = (self.height, self.width);
        let plane = |v: &[f32], f: fn(f32) -> f32| -> Vec<f32> {
            downsample_plane(&v.iter().map(|&a| f(a)).collect::<Vec<_>>(), h, w)
        };
        let atan2 = |s: Vec<f32>, c: Vec<f32>| -> Vec<f32> {
            s.iter().zip(&c).map(|(s, c)| s.atan2(*c)).collect()
        };
        AngleGrid {
            height: h / 2,
            width: w / 2,
            elevation_rad: atan2(
                plane(&self.elevation_rad, f32::sin),
                plane(&self.elevation_rad, f32::cos),
            ),
            azimuth_rad: atan2(
                plane(&self.azimuth_rad, f32::sin),
                plane(&self.azimuth_rad, f32::cos),
            ),
        }
    }

    /// Resample to `height x width` by bilinear interpolation of sin/cos (pixel centres
    /// aligned, azimuth circular, elevation clamped), then atan2. Renders denser grids.
    fn resample(&self, height: usize, width: usize) -> AngleGrid {
        let (h, w) = (self.height, self.width);
        let mut elevation_rad = Vec::with_capacity(height * width);
        let mut azimuth_rad = Vec::with_capacity(height * width);
        let sample = |v: &[f32], y: f32, x: f32, f: fn(f32) -> f32| -> f32 {
            let y = y.clamp(0.0, (h - 1) as f32);
            let y0 = (y.floor() as usize).min(h - 1);
            let y1 = (y0 + 1).min(h - 1);
            let ty = y - y0 as f32;
            let xf = x.floor();
            let tx = x - xf;
            let x0 = (xf as isize).rem_euclid(w as isize) as usize;
            let x1 = (x0 + 1) % w;
            let at = |r: usize, c: usize| f(v[r * w + c]);
            (1.0 - ty) * ((1.0 - tx) * at(y0, x0) + tx * at(y0, x1))
                + ty * ((1.0 - tx) * at(y1, x0) + tx * at(y1, x1))
        };
        for r in 0..height {
            let y = (r as f32 + 0.5) * h as f32 / height as f32 - 0.5;
            for j in 0..width {
                let x = (j as f32 + 0.5) * w as f32 / width as f32 - 0.5;
                let e = &self.elevation_rad;
                let a = &self.azimuth_rad;
                elevation_rad.push(sample(e, y, x, f32::sin).atan2(sample(e, y, x, f32::cos)));
                azimuth_rad.push(sample(a, y, x, f32::sin).atan2(sample(a, y, x, f32::cos)));
            }
        }
        AngleGrid {
            height,
            width,
            elevation_rad,
            azimuth_rad,
        }
    }

    /// Pyramid of `levels` grids, coarsest first, finest = `self`.
    fn pyramid(&self, levels: usize) -> Vec<AngleGrid> {
        let mut out = vec![self.clone()];
        for _ in 1..levels {
            let next = out
                .last()
                .map(AngleGrid::downsample2x)
                .unwrap_or_else(|| self.clone());
            out.push(next);
        }
        out.reverse();
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn device() -> Device {
        Device::flex()
    }

    #[test]
    fn modulated_linear_matches_explicit_per_sample_weights() {
        let dev = device();
        let mut rng = Rng::new(1);
        let layer = ModulatedLinearConfig::new(6, 5, 4).init(&mut rng, &dev);
        let x = rng.normal_tensor([2, 3, 6], &dev);
        let w = rng.normal_tensor([2, 4], &dev);
        let y = tensor_to_vec(layer.forward(x.clone(), w.clone()));
        // Explicit StyleGAN2 formula per sample.
        let s = tensor_to_vec(layer.affine.forward(w));
        let wt = tensor_to_vec(layer.weight.val().mul_scalar(layer.weight_gain));
        let bias = tensor_to_vec(layer.bias.val());
        let xv = tensor_to_vec(x);
        for b in 0..2 {
            for o in 0..5 {
                let wm: Vec<f32> = (0..6).map(|i| wt[o * 6 + i] * s[b * 6 + i]).collect();
                let d = 1.0 / (wm.iter().map(|v| v * v).sum::<f32>() + 1e-8).sqrt();
                for p in 0..3 {
                    let dot: f32 = (0..6).map(|i| wm[i] * xv[(b * 3 + p) * 6 + i]).sum();
                    let v = dot * d + bias[o];
                    let expected = if v > 0.0 { v } else { 0.2 * v } * std::f32::consts::SQRT_2;
                    let got = y[(b * 3 + p) * 5 + o];
                    assert!((got - expected).abs() < 1e-4, "{got} vs {expected}");
                }
            }
        }
    }

    #[test]
    fn fourier_path_equals_explicit_rotated_encoding() {
        let dev = device();
        let mut rng = Rng::new(2);
        let ff = FourierFeaturesConfig::new(4, 3)
            .with_n_freq(3)
            .init(&mut rng, &dev);
        let layer = ModulatedLinearConfig::new(2 + 6, 4, 5).init(&mut rng, &dev);
        let grid = kitti_like_grid(2, 8);
        let x = rng.normal_tensor([2, 16, 2], &dev);
        let w = rng.normal_tensor([2, 5], &dev);
        let shift = tensor_from(vec![0.3, 0.71], [2], &dev);
        let fast = layer.forward_fourier(
            Some(x.clone().reshape([2, 2, 8, 2])),
            false,
            ff.basis(&grid, &dev),
            Some(&ff.rotation(shift)),
            w.clone(),
        );
        // Explicit: encode each sample's rotated grid and concatenate.
        let encs: Vec<Tensor<3>> = [0.3f32, 0.71]
            .iter()
            .map(|s| {
                ff.basis(&grid.with_azimuth_offset(s * TAU), &dev)
                    .unsqueeze_dim::<3>(0)
            })
            .collect();
        let input = Tensor::cat(vec![x, Tensor::cat(encs, 0)], 2);
        let slow = layer.forward(input, w);
        let diff = (fast - slow).abs().max().into_scalar::<f32>();
        assert!(diff < 1e-4, "max diff {diff}");
    }

    #[test]
    fn fourier_layer_upsampling_after_the_product_equals_upsampling_the_input() {
        // up(x) s W^T == up(x s W^T): the layer may multiply at the coarse resolution.
        let dev = device();
        let mut rng = Rng::new(7);
        let ff = FourierFeaturesConfig::new(4, 3)
            .with_n_freq(3)
            .init(&mut rng, &dev);
        let layer = ModulatedLinearConfig::new(5 + 6, 4, 5).init(&mut rng, &dev);
        let grid = kitti_like_grid(4, 16);
        let x = rng.normal_tensor([2, 2, 8, 5], &dev);
        let w = rng.normal_tensor([2, 5], &dev);
        let basis = ff.basis(&grid, &dev);
        let fast = layer.forward_fourier(Some(x.clone()), true, basis.clone(), None, w.clone());
        let x_up = upsample2x(x).reshape([2, 4, 16, 5]);
        let slow = layer.forward_fourier(Some(x_up), false, basis, None, w);
        let diff = (fast - slow).abs().max().into_scalar::<f32>();
        assert!(diff < 1e-5, "max diff {diff}");
    }

    #[test]
    fn fourier_encoding_is_exactly_periodic_in_azimuth() {
        let dev = device();
        let mut rng = Rng::new(3);
        let ff = FourierFeaturesConfig::new(5, 6)
            .with_n_freq(16)
            .init(&mut rng, &dev);
        let grid = kitti_like_grid(4, 16);
        let a = ff.basis(&grid, &dev);
        let b = ff.basis(&grid.with_azimuth_offset(TAU), &dev);
        let diff = (a - b).abs().max().into_scalar::<f32>();
        assert!(diff < 1e-4, "max diff {diff}");
        let b_theta = tensor_to_vec(ff.b_theta.val());
        assert!(b_theta.iter().all(|b| b.fract() == 0.0 && b.abs() <= 32.0));
    }

    #[test]
    fn upsample_preserves_constants_and_is_circular() {
        let dev = device();
        let x = Tensor::<4>::ones([1, 2, 4, 3], &dev).mul_scalar(2.5);
        let y = upsample2x(x);
        assert_eq!(y.dims(), [1, 4, 8, 3]);
        let err = y.sub_scalar(2.5).abs().max().into_scalar::<f32>();
        assert!(err < 1e-6);
        // A one-column roll commutes with upsampling as a two-column roll.
        let mut rng = Rng::new(4);
        let x = rng.normal_tensor([1, 3, 8, 2], &dev);
        let a = roll(upsample2x(x.clone()), 2, 2);
        let b = upsample2x(roll(x, 1, 2));
        assert!((a - b).abs().max().into_scalar::<f32>() < 1e-6);
    }

    #[test]
    fn angle_pyramid_keeps_circular_azimuth() {
        let grid = kitti_like_grid(16, 64);
        let pyr = grid.pyramid(3);
        assert_eq!((pyr[0].height, pyr[0].width), (4, 16));
        // Coarse azimuth equals the regular coarse grid (filter is symmetric about the pair).
        let coarse = kitti_like_grid(4, 16);
        for (a, b) in pyr[0].azimuth_rad.iter().zip(&coarse.azimuth_rad) {
            let d = (a - b + std::f32::consts::PI).rem_euclid(TAU) - std::f32::consts::PI;
            assert!(d.abs() < 1e-4, "{a} vs {b}");
        }
    }
}
