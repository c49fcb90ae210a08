//! What every training run directory shares (the GAN, the encoder, the segmentation
//! network): the backend it computes on, and the checkpoint folder, replaced atomically so a
//! kill leaves the previous checkpoint or the new one.

use std::path::Path;

use anyhow::{Result, bail};
use burn::tensor::Device;
use serde::{Deserialize, Serialize};

pub use crate::model::weights::CHECKPOINT;

/// The burn backend a training run computes on. The CPU ones are always built;
/// the GPU ones need the cargo feature of the same name (`--features cuda` or
/// `--features wgpu`), so the default build needs no GPU toolkit.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Backend {
    Flex,
    Ndarray,
    Cuda,
    Wgpu,
}

impl Backend {
    pub const ALL: [Backend; 4] = [
        Backend::Flex,
        Backend::Ndarray,
        Backend::Cuda,
        Backend::Wgpu,
    ];

    /// The device to compute on, or why this build has none for this backend.
    pub fn device(self) -> Result<Device> {
        match self {
            Backend::Flex => Ok(Device::flex()),
            #[allow(deprecated)]
            Backend::Ndarray => Ok(Device::ndarray()),
            #[cfg(feature = "cuda")]
            Backend::Cuda => Ok(Device::cuda(0)),
            #[cfg(feature = "wgpu")]
            Backend::Wgpu => Ok(Device::wgpu(burn::tensor::DeviceKind::DefaultDevice)),
            #[allow(unreachable_patterns)]
            gpu => bail!(
                "this rangegan-mcap was built without the `{0}` feature; \
                 rebuild with `cargo build --release --features {0}` to train on {0}",
                gpu.name()
            ),
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Backend::Flex => "flex",
            Backend::Ndarray => "ndarray",
            Backend::Cuda => "cuda",
            Backend::Wgpu => "wgpu",
        }
    }
}

impl std::str::FromStr for Backend {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        Backend::ALL
            .into_iter()
            .find(|b| b.name() == s)
            .ok_or_else(|| format!("unknown backend {s:?}: use flex, ndarray, cuda or wgpu"))
    }
}

/// Writes `RUN_DIR/checkpoint/` through `fill` into a temporary folder, then swaps it in, so a
/// kill at any moment leaves the previous checkpoint or the new one, never half of one.
pub(crate) fn write_checkpoint(
    run_dir: &Path,
    fill: impl FnOnce(&Path) -> Result<()>,
) -> Result<()> {
    let tmp = run_dir.join("checkpoint.tmp");
    let old = run_dir.join("checkpoint.old");
    let dst = run_dir.join(CHECKPOINT);
    let _ = std::fs::remove_dir_all(&tmp);
    std::fs::create_dir_all(&tmp)?;
    fill(&tmp)?;
    let _ = std::fs::remove_dir_all(&old);
    if dst.exists() {
        std::fs::rename(&dst, &old)?;
    }
    std::fs::rename(&tmp, &dst)?;
    let _ = std::fs::remove_dir_all(&old);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn backends_parse_by_name_and_the_cpu_ones_always_exist() {
        for b in Backend::ALL {
            assert_eq!(b.name().parse::<Backend>(), Ok(b));
            let json = serde_json::to_string(&b).expect("json");
            assert_eq!(json, format!("\"{}\"", b.name()));
        }
        assert!(Backend::Flex.device().is_ok());
        assert!(Backend::Ndarray.device().is_ok());
        assert!("tpu".parse::<Backend>().is_err());
    }

    #[cfg(not(feature = "cuda"))]
    #[test]
    fn a_gpu_backend_missing_from_the_build_says_which_feature_to_build() {
        let err = Backend::Cuda
            .device()
            .expect_err("no cuda in this build")
            .to_string();
        assert!(err.contains("--features cuda"), "{err}");
    }
}
