//! Where a trained generator comes from: the shipped weights compiled into the binary (so the
//! tool works with no network and no files beside it), a model directory (`config.json` +
//! `g_ema.bpk`, as in `models/`) or a training run directory (its latest checkpoint), each
//! with its optional ray-drop calibration (`calibration.json`, [`super::calibration`]).

use std::path::Path;

use anyhow::{Context, Result};
use burn::module::Module;
use burn::store::ModuleRecord;
use burn::tensor::{Bytes, Device};

use super::calibration::RaydropCalibration;
use super::{AnyGenerator, ModelConfig};

/// A `LABEL=MODEL_DIR` argument of the evaluation tools (`shipped` as the directory, or a
/// bare `shipped`, is the compiled-in model; a bare path labels itself).
pub fn parse_labelled_model(text: &str) -> Result<(String, Option<std::path::PathBuf>), String> {
    let (label, dir) = text.split_once('=').unwrap_or((text, text));
    if label.is_empty() || dir.is_empty() {
        return Err(format!("{text:?}: expected LABEL=MODEL_DIR"));
    }
    Ok((label.to_string(), (dir != "shipped").then(|| dir.into())))
}

/// The folder of a training run's latest checkpoint (`g_ema.bpk` and the rest).
pub const CHECKPOINT: &str = "checkpoint";

/// The shipped model's training configuration.
pub const SHIPPED_CONFIG: &str = include_str!("../../models/dusty2/config.json");
/// The shipped model's EMA generator weights (burnpack).
const SHIPPED_WEIGHTS: &[u8] = include_bytes!("../../models/dusty2/g_ema.bpk");
/// The shipped model's x_n calibration (`rangegan-mcap calibrate-raydrop`).
const SHIPPED_CALIBRATION: &str = include_str!("../../models/dusty2/calibration.json");

/// A trained generator with its configuration.
#[derive(Debug)]
pub struct Model {
    pub generator: AnyGenerator,
    pub config: ModelConfig,
    /// Per-beam calibration of x_n, when one was fitted for these weights.
    pub calibration: Option<RaydropCalibration>,
    /// Where it came from, for reports ("shipped" or a path).
    pub source: String,
}

impl Model {
    /// The weights shipped in `models/dusty2`, compiled into the binary.
    pub fn shipped(device: &Device) -> Result<Self> {
        let config =
            ModelConfig::parse(SHIPPED_CONFIG).context("the shipped model's config.json")?;
        let record = ModuleRecord::from_bytes(Bytes::from_bytes_vec(SHIPPED_WEIGHTS.to_vec()))
            .map_err(|e| anyhow::anyhow!("the shipped weights are unreadable: {e}"))?;
        let generator = config
            .init_generator(device)
            .try_load_record(record)
            .map_err(|e| anyhow::anyhow!("the shipped weights do not fit their config: {e}"))?;
        Ok(Self {
            generator,
            config,
            calibration: Some(RaydropCalibration::from_json(
                SHIPPED_CALIBRATION,
                "models/dusty2/calibration.json",
            )?),
            source: "shipped".into(),
        })
    }

    /// A model directory (`config.json`, `g_ema.bpk`) or a run directory
    /// (`config.json`, `checkpoint/g_ema.bpk`).
    pub fn from_dir(dir: &Path, device: &Device) -> Result<Self> {
        let config = ModelConfig::load(&dir.join("config.json"))?;
        let direct = dir.join("g_ema.bpk");
        let path = if direct.is_file() {
            direct
        } else {
            dir.join(CHECKPOINT).join("g_ema.bpk")
        };
        let generator = config
            .init_generator(device)
            .try_load_file(&path)
            .map_err(|e| anyhow::anyhow!("failed to load '{}': {e}", path.display()))?;
        let calibration_path = dir.join("calibration.json");
        let calibration = if calibration_path.is_file() {
            let text = std::fs::read_to_string(&calibration_path)
                .with_context(|| format!("failed to read '{}'", calibration_path.display()))?;
            Some(RaydropCalibration::from_json(
                &text,
                &calibration_path.display().to_string(),
            )?)
        } else {
            None
        };
        Ok(Self {
            generator,
            config,
            calibration,
            source: dir.display().to_string(),
        })
    }

    /// `--model DIR` if given, else the shipped weights.
    pub fn load(dir: Option<&Path>, device: &Device) -> Result<Self> {
        match dir {
            Some(d) => Self::from_dir(d, device),
            None => Self::shipped(device),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::util::rng::Rng;
    use crate::util::tensor::tensor_to_vec;

    #[test]
    fn labelled_models_parse() {
        assert_eq!(
            parse_labelled_model("shipped"),
            Ok(("shipped".into(), None))
        );
        assert_eq!(
            parse_labelled_model("run=runs/a"),
            Ok(("run".into(), Some("runs/a".into())))
        );
        assert!(parse_labelled_model("=x").is_err());
    }

    #[test]
    fn shipped_weights_load_and_match_the_model_directory() {
        let device = Device::flex();
        let shipped = Model::shipped(&device).expect("shipped model");
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("models/dusty2");
        let from_dir = Model::from_dir(&dir, &device).expect("model dir");
        let grid = crate::lidar::SensorProfile::kitti_hdl64e()
            .with_columns(64)
            .angle_grid();
        let render = |m: &Model| {
            let AnyGenerator::Implicit(g) = &m.generator else {
                panic!("the shipped model is the implicit generator")
            };
            let z = Rng::new(3).normal_tensor([1, g.d_z()], &device);
            let cache = g.prepare(&grid, &device);
            tensor_to_vec(g.render(g.mapping.forward(z), &cache, None).x_d)
        };
        let (a, b) = (render(&shipped), render(&from_dir));
        assert_eq!(a, b);
        assert!(shipped.calibration.is_some());
        assert_eq!(shipped.calibration, from_dir.calibration);
        // trained weights, not an initialisation: the output varies across the image
        let spread =
            a.iter().cloned().fold(f32::MIN, f32::max) - a.iter().cloned().fold(f32::MAX, f32::min);
        assert!(spread > 0.1, "spread {spread}");
    }
}
