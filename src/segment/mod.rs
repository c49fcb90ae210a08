//! Range-image semantic segmentation, the downstream task of the Sim2Real benchmark
//! (the seed paper's Table 4): a network trained on labelled simulated scans, with or without
//! rendered ray drop, judged on labelled real scans.
//!
//! - [`classes`]: the scored classes and the SemanticKITTI ids behind them.
//! - [`data`]: "C R M" inputs (x, y, z, range, return mask) and targets from recordings.
//! - [`loss`]: class-weighted cross-entropy and Lovász-softmax.
//! - [`net`]: a light U-Net with circular padding along azimuth.
//! - [`train`]: the training loop with checkpoints, resume and the exported model.
//! - [`eval`]: per-class precision, recall and IoU, mean IoU, and comparison pictures.
//!
//! A model folder holds `segment.json` ([`SegModelInfo`]) and `net.bpk`.

pub mod classes;
pub mod data;
pub mod eval;
pub mod loss;
pub mod net;
pub mod train;

use std::path::Path;

use anyhow::{Context, Result};
use burn::module::Module;
use burn::tensor::Device;
use serde::{Deserialize, Serialize};

use crate::lidar::SensorProfile;
use net::{SegNet, SegNetConfig};

/// What a model folder says about its network.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SegModelInfo {
    pub net: SegNetConfig,
    /// Output classes, in order.
    pub classes: Vec<String>,
    /// The grid inputs are projected on.
    pub profile: SensorProfile,
    /// Training recordings (file names) and the run's settings.
    pub trained_on: Vec<String>,
    pub steps: u64,
    pub seed: u64,
}

/// A trained network, ready for inference.
#[derive(Debug)]
pub struct SegModel {
    pub info: SegModelInfo,
    pub net: SegNet,
}

impl SegModel {
    pub const INFO: &'static str = "segment.json";
    pub const WEIGHTS: &'static str = "net.bpk";

    pub fn load(dir: &Path, device: &Device) -> Result<Self> {
        let info_path = dir.join(Self::INFO);
        let text = std::fs::read_to_string(&info_path).with_context(|| {
            format!(
                "{}: not a segmentation model folder (no {})",
                dir.display(),
                Self::INFO
            )
        })?;
        let info: SegModelInfo = serde_json::from_str(&text)
            .with_context(|| format!("{}: bad model description", info_path.display()))?;
        anyhow::ensure!(
            info.classes == classes::CLASSES,
            "{}: classes {:?} differ from this version's {:?}",
            info_path.display(),
            info.classes,
            classes::CLASSES
        );
        info.net
            .check()
            .with_context(|| format!("{}: bad network size", info_path.display()))?;
        let net = info
            .net
            // The loaded weights replace the drawn ones: the seed does not matter.
            .init(&mut crate::util::rng::Rng::new(0), device)
            .try_load_file(dir.join(Self::WEIGHTS))
            .map_err(|e| anyhow::anyhow!("{}: cannot load weights: {e}", dir.display()))?;
        Ok(SegModel { info, net })
    }

    /// Writes `dir` (created if absent); the weights go through a temporary file.
    pub fn save(info: &SegModelInfo, net: &SegNet, dir: &Path) -> Result<()> {
        std::fs::create_dir_all(dir)?;
        let tmp = dir.join("net.bpk.tmp");
        net.clone()
            .save_file(&tmp)
            .map_err(|e| anyhow::anyhow!("cannot save {}: {e}", tmp.display()))?;
        std::fs::rename(&tmp, dir.join(Self::WEIGHTS))?;
        crate::util::fs::write_atomic(
            &dir.join(Self::INFO),
            serde_json::to_string_pretty(info)?.as_bytes(),
        )?;
        Ok(())
    }
}
