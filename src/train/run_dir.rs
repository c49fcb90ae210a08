//! What every training run directory shares (the GAN, the encoder, the segmentation
//! network): the backend it computes on, the checkpoint folder, replaced atomically so a
//! kill leaves the previous checkpoint or the new one, and the JSONL log, which holds each
//! step the checkpoint has trained exactly once.

use std::fs::{File, OpenOptions};
use std::path::Path;

use anyhow::{Context, Result, bail};
use burn::tensor::Device;
use serde::de::DeserializeOwned;
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

/// The training state a checkpoint folder saved in its `state.json`.
pub(crate) fn read_state<T: DeserializeOwned>(checkpoint: &Path) -> Result<T> {
    let path = checkpoint.join("state.json");
    let text = std::fs::read_to_string(&path)
        .with_context(|| format!("failed to read '{}'", path.display()))?;
    serde_json::from_str(&text).with_context(|| format!("bad '{}'", path.display()))
}

/// Opens `RUN_DIR/log.jsonl` for appending from a checkpoint at `step` (0 for a fresh run).
/// A run killed between checkpoints logged steps its checkpoint never kept; the resumed run
/// trains them again, so their old lines are dropped first (atomically) and the log holds
/// every step once, in order.
pub(crate) fn open_log(run_dir: &Path, step: u64) -> Result<File> {
    let path = run_dir.join("log.jsonl");
    if let Ok(text) = std::fs::read_to_string(&path) {
        let kept = log_through(&text, step);
        if kept.len() < text.len() {
            let tmp = run_dir.join("log.jsonl.tmp");
            std::fs::write(&tmp, kept)
                .and_then(|()| std::fs::rename(&tmp, &path))
                .with_context(|| format!("failed to rewrite '{}'", path.display()))?;
        }
    }
    OpenOptions::new()
        .create(true)
        .append(true)
        .open(&path)
        .with_context(|| format!("failed to open '{}'", path.display()))
}

/// The lines of a JSONL training log up to and including `step`. A line's step is its
/// `step` field or its `validation.step`; lines with neither (and lines that are not JSON)
/// are kept, since nothing says they came later.
pub(crate) fn log_through(text: &str, step: u64) -> String {
    let line_step = |line: &str| {
        let value: serde_json::Value = serde_json::from_str(line).ok()?;
        value["step"]
            .as_u64()
            .or_else(|| value["validation"]["step"].as_u64())
    };
    text.split_inclusive('\n')
        .filter(|line| line_step(line).is_none_or(|s| s <= step))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_log_keeps_the_lines_through_the_checkpoint_step() {
        let log = "{\"step\":10}\n{\"validation\":{\"step\":10,\"miou\":0.5}}\n\
                   {\"step\":20}\nnot json\n{\"validation\":{\"step\":30}}\n{\"step\":30}\n";
        assert_eq!(
            log_through(log, 20),
            "{\"step\":10}\n{\"validation\":{\"step\":10,\"miou\":0.5}}\n{\"step\":20}\nnot json\n"
        );
        assert_eq!(log_through(log, 30), log);
        assert_eq!(log_through(log, 0), "not json\n");
    }

    #[test]
    fn a_resumed_log_drops_the_steps_trained_again_and_appends() {
        let tmp = tempfile::tempdir().expect("tempdir");
        let dir = tmp.path();
        {
            use std::io::Write;
            let mut log = open_log(dir, 0).expect("fresh log");
            writeln!(log, "{{\"step\":1}}\n{{\"step\":2}}\n{{\"step\":3}}").expect("write");
        }
        {
            use std::io::Write;
            let mut log = open_log(dir, 2).expect("resumed log");
            writeln!(log, "{{\"step\":3,\"again\":true}}").expect("write");
        }
        let text = std::fs::read_to_string(dir.join("log.jsonl")).expect("log");
        assert_eq!(
            text,
            "{\"step\":1}\n{\"step\":2}\n{\"step\":3,\"again\":true}\n"
        );
        assert!(!dir.join("log.jsonl.tmp").exists());
    }

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
