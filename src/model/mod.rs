//! The range-image GAN of the seed paper (DUSty v2) and its two baselines, in burn.
//!
//! - [`layers`]: modulated layers, Fourier features, resampling filter, angle grids.
//! - [`generator`]: the implicit DUSty v2 generator (z -> w -> x_d, keep logit on any grid).
//! - [`baseline`]: fixed-resolution transposed-conv generator (DUSty v1, vanilla).
//! - [`measurement`]: the differentiable ray-drop model (keep/drop probability, sampled masks).
//! - [`conv`]: circular convolutions (padding, blur-downsampling, plain and modulated 3x3).
//! - [`discriminator`]: circular residual discriminator.
//! - [`data`]: the projected-dataset cache.
//! - [`config`]: what a trained generator is (family, shapes, measurement).
//! - [`weights`]: the shipped model and loading trained generators.
//! - [`sample`], [`metrics`], [`two_sample`]: drawing scans, SWD, the classifier two-sample test.
//!
//! Images are in network units: inverse depth x_d = 1.45 m / depth in [0.018, 1] mapped to
//! 2 x_d - 1, no return = -1. The backend/device is chosen by the caller.

pub mod baseline;
pub mod calibration;
pub mod config;
pub mod conv;
pub mod data;
pub mod discriminator;
pub mod generator;
pub mod layers;
pub mod measurement;
pub mod metrics;
pub mod sample;
pub mod self_decoder;
pub mod spatial;
pub mod two_sample;
pub mod weights;

use burn::module::Module;
use burn::tensor::Tensor;
use serde::{Deserialize, Serialize};

use baseline::ConvGenerator;
use generator::{Generator, GridCache};

/// Make glibc's malloc keep freed tensor buffers for reuse instead of handing them back to the
/// kernel. By default every buffer above 128 KiB (the threshold then adapts, up to 32 MiB) is
/// its own mmap, and the top of the heap is trimmed at 128 KiB of free space, so each training
/// or inversion step re-faults and re-zeroes tens of MB of fresh pages: 20 % of the CPU time of
/// a reference-size inversion step (docs/model_benchmarks.md). With the thresholds raised,
/// buffers up to 32 MiB come from the heap and stay mapped; the cost is that the process keeps
/// its peak heap size until exit. No-op outside Linux/glibc. Call once, before the first tensor.
pub fn tune_allocator() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only changes malloc tunables; both values are in range (glibc caps
    // M_MMAP_THRESHOLD at 32 MiB on 64-bit).
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 32 << 20);
        libc::mallopt(libc::M_TRIM_THRESHOLD, 1 << 30);
    }
}

/// Which generator family (the paper's comparison).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Arch {
    /// Implicit generator + measurement model (the paper's method).
    Dusty2,
    /// Transposed-conv generator + measurement model.
    Dusty1,
    /// Transposed-conv generator learning raw images.
    Vanilla,
}

impl Arch {
    pub fn has_measurement_model(self) -> bool {
        !matches!(self, Arch::Vanilla)
    }
}

impl std::str::FromStr for Arch {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "dusty2" => Ok(Arch::Dusty2),
            "dusty1" => Ok(Arch::Dusty1),
            "vanilla" => Ok(Arch::Vanilla),
            other => Err(format!(
                "unknown arch {other:?}: use dusty2, dusty1 or vanilla"
            )),
        }
    }
}

pub use config::ModelConfig;

/// Any of the three generators behind one interface.
#[allow(clippy::large_enum_variant)] // one generator per run; never stored in bulk
#[derive(Module, Debug)]
pub enum AnyGenerator {
    Implicit(Generator),
    Conv(ConvGenerator),
}

/// What a generator produces, network units, `[batch, 1, H, W]`.
#[derive(Debug, Clone)]
pub struct Generated {
    /// Inverse depth before ray drop (vanilla: the raw image).
    pub x_d: Tensor<4>,
    /// Keep logit (None for vanilla).
    pub keep_logit: Option<Tensor<4>>,
}

impl AnyGenerator {
    pub fn d_z(&self) -> usize {
        match self {
            AnyGenerator::Implicit(g) => g.d_z(),
            AnyGenerator::Conv(g) => g.d_z(),
        }
    }

    /// Generate from z. The implicit generator needs `grid` and may use a subgrid shift; the
    /// conv generators ignore both.
    pub fn generate(
        &self,
        z: Tensor<2>,
        grid: Option<&GridCache>,
        subgrid_shift: Option<&[f32]>,
    ) -> (Generated, Option<Tensor<2>>) {
        match self {
            AnyGenerator::Implicit(g) => {
                let grid = grid.expect("the implicit generator needs an angle grid");
                let w = g.mapping.forward(z);
                let out = g.render(w.clone(), grid, subgrid_shift);
                (
                    Generated {
                        x_d: out.x_d,
                        keep_logit: Some(out.keep_logit),
                    },
                    Some(w),
                )
            }
            AnyGenerator::Conv(g) => {
                let y = g.forward(z);
                let c = y.dims()[1];
                let x_d = y.clone().narrow(1, 0, 1);
                let keep_logit = (c > 1).then(|| y.narrow(1, 1, 1));
                (Generated { x_d, keep_logit }, None)
            }
        }
    }
}
