//! What a trained generator is, as its folder's `config.json` records it: the family, the
//! shape of its generator, the ray-drop measurement and the sensor it was trained for. A training run's config carries the
//! same fields beside its training settings, so a run directory loads as a model too.

use std::path::Path;

use anyhow::{Context, Result};
use burn::tensor::Device;
use serde::{Deserialize, Serialize};

use super::baseline::ConvGeneratorConfig;
use super::data::DepthRange;
use super::generator::GeneratorConfig;
use super::measurement::MeasurementConfig;
use super::{AnyGenerator, Arch};
use crate::lidar::{AngleGrid, SensorProfile};

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ModelConfig {
    pub arch: Arch,
    /// The implicit generator (`dusty2`).
    pub generator: GeneratorConfig,
    /// The transposed-conv generator: `dusty1` (2 output channels) and `vanilla` (1).
    pub conv_generator: ConvGeneratorConfig,
    pub measurement: MeasurementConfig,
    /// The sensor the model was trained for, at its training columns: its beams and columns
    /// are the model grid, its valid range the network units ([`DepthRange::of`]). Models
    /// written before it was recorded were all trained on KITTI's HDL-64E at 512 columns.
    pub sensor: SensorProfile,
}

/// The sensor of a model whose config does not name one.
pub fn default_sensor() -> SensorProfile {
    SensorProfile::kitti_hdl64e().with_columns(512)
}

impl Default for ModelConfig {
    fn default() -> Self {
        Self {
            arch: Arch::Dusty2,
            generator: GeneratorConfig::cpu(),
            conv_generator: ConvGeneratorConfig::cpu(2),
            measurement: MeasurementConfig::new(),
            sensor: default_sensor(),
        }
    }
}

impl ModelConfig {
    /// Reads a model's or a run's `config.json`; other keys are ignored, and fields added
    /// after the file was written take their defaults.
    pub fn parse(text: &str) -> Result<Self> {
        let saved: serde_json::Value = serde_json::from_str(text).context("not JSON")?;
        let mut merged = serde_json::to_value(Self::default())?;
        crate::util::json::merge(&mut merged, saved);
        Ok(serde_json::from_value(merged)?)
    }

    /// [`Self::parse`] on a file, with its sizes checked before anything is built.
    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("failed to read '{}'", path.display()))?;
        let config =
            Self::parse(&text).with_context(|| format!("bad config '{}'", path.display()))?;
        config
            .check()
            .with_context(|| format!("{}: bad generator config", path.display()))?;
        Ok(config)
    }

    /// The grid the model was trained on (and inverts on).
    pub fn grid(&self) -> AngleGrid {
        self.sensor.angle_grid()
    }

    /// The model's network units.
    pub fn depth_range(&self) -> DepthRange {
        DepthRange::of(&self.sensor)
    }

    /// Refuses generator sizes that cannot be built.
    pub fn check(&self) -> Result<()> {
        self.sensor
            .validate()
            .map_err(|e| anyhow::anyhow!("sensor: {e}"))?;
        anyhow::ensure!(
            self.sensor.min_range_m > 0.0,
            "sensor: a model's nearest valid depth must be above 0 m (it scales x_d = min / depth)"
        );
        match self.arch {
            Arch::Dusty2 => self.generator.check(),
            _ => self.conv_generator.check(),
        }
    }

    /// A generator of this shape with fresh weights.
    pub fn init_generator(&self, device: &Device) -> AnyGenerator {
        match self.arch {
            Arch::Dusty2 => AnyGenerator::Implicit(self.generator.init(device)),
            Arch::Dusty1 => AnyGenerator::Conv(
                self.conv_generator
                    .clone()
                    .with_out_channels(2)
                    .init(device),
            ),
            Arch::Vanilla => AnyGenerator::Conv(
                self.conv_generator
                    .clone()
                    .with_out_channels(1)
                    .init(device),
            ),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A training run's config reads as a model config: its training keys are ignored.
    #[test]
    fn a_run_config_reads_as_its_model() {
        let text = r#"{"arch": "dusty1", "batch_size": 32, "measurement": {"tau": 0.5}}"#;
        let c = ModelConfig::parse(text).unwrap();
        assert_eq!(c.arch, Arch::Dusty1);
        assert_eq!(c.measurement.tau, 0.5);
        assert_eq!(
            c.generator.channels,
            GeneratorConfig::cpu().channels,
            "missing fields take their defaults"
        );
        assert_eq!(
            c.sensor,
            default_sensor(),
            "a config without a sensor is KITTI's"
        );
        assert!(ModelConfig::parse("[1, 2]").is_err());
    }
}
