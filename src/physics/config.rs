//! Which effects are on, with which parameters: a [`PhysicsConfig`] read from a
//! JSON file (`schemas/physics.schema.json`) or taken from a [`Preset`], checked,
//! and turned into a [`Physics`] pipeline in a fixed physical order.

use std::collections::BTreeMap;
use std::path::Path;

use serde::{Deserialize, Serialize};

use super::dropout::{
    BeamDropout, EdgeDropout, IncidenceDropout, IntensityDropout, MaterialDropout, OcclusionSector,
    RangeDropout, SelfOcclusion, UniformDropout,
};
use super::perturb::{
    Atmosphere, IntensityNoise, MixedPixels, MotionDistortion, RangeNoise, RangeQuantization,
};
use super::{Effect, Physics};
use crate::sim::Material;
use crate::util::rng::gaussian;

/// Errors loading or checking physics; each names the file or the parameter.
#[derive(Debug, thiserror::Error)]
pub enum PhysicsError {
    #[error(
        "unknown physics preset '{0}' (presets: ideal, carla-like, realistic); or give a physics JSON file"
    )]
    UnknownPreset(String),
    #[error("{path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
    #[error("{path}: {source} (schema: schemas/physics.schema.json)")]
    Json {
        path: String,
        source: serde_json::Error,
    },
    #[error("{path}: parameter {parameter} = {value}: {reason}")]
    Invalid {
        path: String,
        parameter: String,
        value: String,
        reason: String,
    },
}

/// The effect parameters, one optional entry per catalogue id. A missing entry or
/// `"enabled": false` switches the effect off; all off = the ideal simulator.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PhysicsConfig {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub description: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub self_occlusion: Option<SelfOcclusion>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub beam_dropout: Option<BeamDropout>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub range_dropout: Option<RangeDropout>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub incidence_dropout: Option<IncidenceDropout>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub material_dropout: Option<MaterialDropout>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub edge_dropout: Option<EdgeDropout>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub uniform_dropout: Option<UniformDropout>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub intensity_dropout: Option<IntensityDropout>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub atmosphere: Option<Atmosphere>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mixed_pixels: Option<MixedPixels>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub range_noise: Option<RangeNoise>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub range_quantization: Option<RangeQuantization>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub motion_distortion: Option<MotionDistortion>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub intensity_noise: Option<IntensityNoise>,
}

/// Built-in physics.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Preset {
    /// No effects: the ideal ray caster.
    Ideal,
    /// What CARLA's ray-cast lidar does: uniform drops (`dropoff_general_rate`
    /// 0.45) and the intensity-threshold drop (limit 0.8, prob 0.4, 0.004 /m).
    CarlaLike,
    /// Every catalogue effect at typical real values, tuned against real KITTI
    /// HDL-64E scans (docs/simulator.md).
    Realistic,
}

impl Preset {
    pub const NAMES: [&'static str; 3] = ["ideal", "carla-like", "realistic"];

    pub fn from_name(name: &str) -> Option<Preset> {
        match name.to_ascii_lowercase().as_str() {
            "ideal" => Some(Preset::Ideal),
            "carla-like" | "carla" => Some(Preset::CarlaLike),
            "realistic" => Some(Preset::Realistic),
            _ => None,
        }
    }

    /// The preset for KITTI's 64-beam HDL-64E.
    pub fn config(self) -> PhysicsConfig {
        self.config_for_beams(64)
    }

    /// The preset for a sensor with `beams` beams (per-beam lists get one entry
    /// per beam: the upper half of the beams as KITTI's upper laser block).
    pub fn config_for_beams(self, beams: usize) -> PhysicsConfig {
        match self {
            Preset::Ideal => PhysicsConfig {
                description: Some("ideal: no sensor physics".into()),
                ..Default::default()
            },
            Preset::CarlaLike => PhysicsConfig {
                description: Some(
                    "carla-like: uniform + intensity-threshold drop, as CARLA's ray-cast lidar"
                        .into(),
                ),
                uniform_dropout: Some(UniformDropout {
                    enabled: true,
                    prob: 0.45,
                }),
                intensity_dropout: Some(IntensityDropout {
                    enabled: true,
                    attenuation_per_m: 0.004,
                    intensity_limit: 0.8,
                    prob: 0.4,
                }),
                ..Default::default()
            },
            Preset::Realistic => realistic(beams),
        }
    }
}

/// The `realistic` preset: KITTI HDL-64E-like values (tuning in docs/simulator.md).
fn realistic(beams: usize) -> PhysicsConfig {
    let mut material = BTreeMap::new();
    material.insert(Material::Glass, 0.35);
    material.insert(Material::DarkPaint, 0.1);
    material.insert(Material::Rubber, 0.2);
    PhysicsConfig {
        description: Some("realistic: every catalogue effect at typical real HDL-64E values, tuned against KITTI".into()),
        // KITTI's blind spots below the roof-mounted HDL-64E, read off the keep
        // map of 254 real scans (docs/simulator.md): rear, front (bonnet), right
        // (roof-rack mount) and both rear quarters.
        self_occlusion: Some(SelfOcclusion {
            enabled: true,
            sectors: vec![
                sector(156.0, -156.0, -18.0, 1.0),
                sector(150.0, -150.0, -13.0, 0.3),
                sector(-80.0, -57.0, -15.3, 1.0),
                sector(-13.0, 13.0, -20.5, 0.6),
                sector(126.0, 142.0, -19.3, 0.7),
                sector(-146.0, -126.0, -19.3, 0.7),
                // The lowest three beams clip the bonnet and the roof edges widely.
                sector(-45.0, 45.0, -21.9, 0.45),
                sector(120.0, 150.0, -21.9, 0.8),
                sector(-150.0, -120.0, -21.9, 0.8),
            ],
            boxes: vec![],
        }),
        // Upper-block lasers (rows 0-31) drop more than lower-block ones.
        beam_dropout: Some(BeamDropout {
            enabled: true,
            rates: Some(
                (0..beams)
                    .map(|row| if row < beams / 2 { 0.025 } else { 0.008 } * (1.0 + 0.5 * gaussian(&[64, row as u64]).clamp(-1.8, 1.8)))
                    .collect(),
            ),
            mean_rate: 0.0,
            spread: 0.0,
            beam_seed: 0,
            dead_beams: vec![],
        }),
        range_dropout: Some(RangeDropout { enabled: true, range_50_m: 150.0, softness: 0.6 }),
        incidence_dropout: Some(IncidenceDropout { enabled: true, cos_50: 0.03, softness: 0.3 }),
        edge_dropout: None,
        material_dropout: Some(MaterialDropout { enabled: true, drop_prob: material, drop_prob_by_class: BTreeMap::new() }),
        // KITTI's HDL-64E fires ~2010 times per turn: at 512 columns ~2 % of the
        // pixels stay empty whatever the scene.
        uniform_dropout: Some(UniformDropout { enabled: true, prob: 0.02 }),
        intensity_dropout: None,
        atmosphere: None,
        mixed_pixels: Some(MixedPixels { enabled: true, prob: 0.3, min_gap_m: 1.0 }),
        range_noise: Some(RangeNoise { enabled: true, sigma0_m: 0.02, k: 0.0005 }),
        range_quantization: Some(RangeQuantization { enabled: true, step_m: 0.002 }),
        motion_distortion: Some(MotionDistortion { enabled: true, scale: 1.0, speed_mps: None }),
        intensity_noise: Some(IntensityNoise { enabled: true, sigma_rel: 0.1 }),
    }
}

fn sector(
    azimuth_min_deg: f32,
    azimuth_max_deg: f32,
    elevation_max_deg: f32,
    prob: f32,
) -> OcclusionSector {
    OcclusionSector {
        azimuth_min_deg,
        azimuth_max_deg,
        elevation_max_deg,
        prob,
    }
}

fn check(
    ok: bool,
    path: &str,
    parameter: &str,
    value: impl std::fmt::Debug,
    reason: &str,
) -> Result<(), PhysicsError> {
    if ok {
        Ok(())
    } else {
        Err(PhysicsError::Invalid {
            path: path.into(),
            parameter: parameter.into(),
            value: format!("{value:?}"),
            reason: reason.into(),
        })
    }
}

fn prob(p: f32) -> bool {
    (0.0..=1.0).contains(&p)
}

/// An edge effect's rates by distance: at most 8 distances, each a probability.
fn check_edge_rates(o: &str, parameter: &str, rates: &[f32]) -> Result<(), PhysicsError> {
    check(
        rates.len() <= usize::from(crate::lidar::edges::MAX_EDGE_PX),
        o,
        parameter,
        rates.len(),
        "lists at most 8 distances (0-7 pixels from the edge)",
    )?;
    for (d, p) in rates.iter().enumerate() {
        check(
            prob(*p),
            o,
            &format!("{parameter}[{d}]"),
            p,
            "must be in [0, 1]",
        )?;
    }
    Ok(())
}

impl PhysicsConfig {
    /// A preset name or a path to a physics JSON file.
    pub fn resolve(name_or_path: &str) -> Result<Self, PhysicsError> {
        Self::resolve_for_beams(name_or_path, 64)
    }

    /// As [`PhysicsConfig::resolve`], presets made for a sensor with `beams` beams.
    pub fn resolve_for_beams(name_or_path: &str, beams: usize) -> Result<Self, PhysicsError> {
        match Preset::from_name(name_or_path) {
            Some(p) => Ok(p.config_for_beams(beams)),
            None if Path::new(name_or_path).exists() => Self::load(Path::new(name_or_path)),
            None => Err(PhysicsError::UnknownPreset(name_or_path.into())),
        }
    }

    pub fn load(path: &Path) -> Result<Self, PhysicsError> {
        let p = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|source| PhysicsError::Io {
            path: p.clone(),
            source,
        })?;
        let config: PhysicsConfig =
            serde_json::from_str(&text).map_err(|source| PhysicsError::Json {
                path: p.clone(),
                source,
            })?;
        config.validate(&p, None)?;
        Ok(config)
    }

    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(self).unwrap_or_default()
    }

    /// Checks every parameter's range; `beams` (if known) checks per-beam lists.
    /// `origin` names the file (or preset) in errors. One flat check per field, in the
    /// order of `schemas/physics.schema.json`, so the two are read side by side: long, not
    /// deep.
    pub fn validate(&self, origin: &str, beams: Option<usize>) -> Result<(), PhysicsError> {
        let o = origin;
        if let Some(e) = &self.self_occlusion {
            for (i, s) in e.sectors.iter().enumerate() {
                check(
                    prob(s.prob),
                    o,
                    &format!("self_occlusion.sectors[{i}].prob"),
                    s.prob,
                    "must be in [0, 1]",
                )?;
                let az = |a: f32| (-180.0..=180.0).contains(&a);
                check(
                    az(s.azimuth_min_deg) && az(s.azimuth_max_deg),
                    o,
                    &format!("self_occlusion.sectors[{i}].azimuth"),
                    (s.azimuth_min_deg, s.azimuth_max_deg),
                    "azimuths are in [-180, 180] deg",
                )?;
            }
            for (i, b) in e.boxes.iter().enumerate() {
                check(
                    prob(b.prob),
                    o,
                    &format!("self_occlusion.boxes[{i}].prob"),
                    b.prob,
                    "must be in [0, 1]",
                )?;
                check(
                    (0..3).all(|a| b.min_m[a] <= b.max_m[a]),
                    o,
                    &format!("self_occlusion.boxes[{i}].min_m"),
                    b.min_m,
                    "must be <= max_m on every axis",
                )?;
            }
        }
        if let Some(e) = &self.beam_dropout {
            check(
                prob(e.mean_rate),
                o,
                "beam_dropout.mean_rate",
                e.mean_rate,
                "must be in [0, 1]",
            )?;
            check(
                e.spread >= 0.0 && e.spread.is_finite(),
                o,
                "beam_dropout.spread",
                e.spread,
                "must be >= 0",
            )?;
            if let Some(r) = &e.rates {
                check(
                    r.iter().all(|x| prob(*x)),
                    o,
                    "beam_dropout.rates",
                    r,
                    "every rate must be in [0, 1]",
                )?;
                if let Some(b) = beams {
                    check(
                        r.len() == b,
                        o,
                        "beam_dropout.rates",
                        r.len(),
                        &format!("needs one rate per beam ({b})"),
                    )?;
                }
            }
            if let Some(b) = beams {
                check(
                    e.dead_beams.iter().all(|&d| d < b),
                    o,
                    "beam_dropout.dead_beams",
                    &e.dead_beams,
                    &format!("beams are 0..{b}"),
                )?;
            }
        }
        if let Some(e) = &self.range_dropout {
            check(
                e.range_50_m > 0.0,
                o,
                "range_dropout.range_50_m",
                e.range_50_m,
                "must be > 0",
            )?;
            check(
                e.softness > 0.0,
                o,
                "range_dropout.softness",
                e.softness,
                "must be > 0",
            )?;
        }
        if let Some(e) = &self.incidence_dropout {
            check(
                e.cos_50 > 0.0 && e.cos_50 < 1.0,
                o,
                "incidence_dropout.cos_50",
                e.cos_50,
                "must be in (0, 1)",
            )?;
            check(
                e.softness > 0.0,
                o,
                "incidence_dropout.softness",
                e.softness,
                "must be > 0",
            )?;
        }
        if let Some(e) = &self.edge_dropout {
            check_edge_rates(o, "edge_dropout.drop_prob_by_px", &e.drop_prob_by_px)?;
            check(
                e.bands.is_empty() || e.drop_prob_by_px.is_empty(),
                o,
                "edge_dropout",
                "drop_prob_by_px and bands",
                "gives either drop_prob_by_px or bands, not both",
            )?;
            for (b, band) in e.bands.iter().enumerate() {
                let rises = match b.checked_sub(1) {
                    None => band.from_m == 0.0,
                    Some(previous) => band.from_m > e.bands[previous].from_m,
                };
                check(
                    rises,
                    o,
                    &format!("edge_dropout.bands[{b}].from_m"),
                    band.from_m,
                    "must start at 0 and rise band by band",
                )?;
                check_edge_rates(
                    o,
                    &format!("edge_dropout.bands[{b}].drop_prob_by_px"),
                    &band.drop_prob_by_px,
                )?;
            }
        }
        if let Some(e) = &self.material_dropout {
            for (m, p) in &e.drop_prob {
                check(
                    prob(*p),
                    o,
                    &format!("material_dropout.drop_prob.{}", m.name()),
                    p,
                    "must be in [0, 1]",
                )?;
            }
            for (c, p) in &e.drop_prob_by_class {
                check(
                    prob(*p),
                    o,
                    &format!("material_dropout.drop_prob_by_class.{c}"),
                    p,
                    "must be in [0, 1]",
                )?;
            }
        }
        if let Some(e) = &self.uniform_dropout {
            check(
                prob(e.prob),
                o,
                "uniform_dropout.prob",
                e.prob,
                "must be in [0, 1]",
            )?;
        }
        if let Some(e) = &self.intensity_dropout {
            check(
                prob(e.prob),
                o,
                "intensity_dropout.prob",
                e.prob,
                "must be in [0, 1]",
            )?;
            check(
                e.attenuation_per_m >= 0.0,
                o,
                "intensity_dropout.attenuation_per_m",
                e.attenuation_per_m,
                "must be >= 0",
            )?;
        }
        if let Some(e) = &self.atmosphere {
            check(
                e.extinction_per_m >= 0.0,
                o,
                "atmosphere.extinction_per_m",
                e.extinction_per_m,
                "must be >= 0",
            )?;
            check(
                prob(e.clutter_prob),
                o,
                "atmosphere.clutter_prob",
                e.clutter_prob,
                "must be in [0, 1]",
            )?;
            check(
                e.clutter_mean_range_m > 0.0,
                o,
                "atmosphere.clutter_mean_range_m",
                e.clutter_mean_range_m,
                "must be > 0",
            )?;
        }
        if let Some(e) = &self.mixed_pixels {
            check(
                prob(e.prob),
                o,
                "mixed_pixels.prob",
                e.prob,
                "must be in [0, 1]",
            )?;
            check(
                e.min_gap_m >= 0.0,
                o,
                "mixed_pixels.min_gap_m",
                e.min_gap_m,
                "must be >= 0",
            )?;
        }
        if let Some(e) = &self.range_noise {
            check(
                e.sigma0_m >= 0.0 && e.k >= 0.0,
                o,
                "range_noise.sigma0_m/k",
                (e.sigma0_m, e.k),
                "must be >= 0",
            )?;
        }
        if let Some(e) = &self.range_quantization {
            check(
                e.step_m >= 0.0,
                o,
                "range_quantization.step_m",
                e.step_m,
                "must be >= 0",
            )?;
        }
        if let Some(e) = &self.motion_distortion {
            check(
                e.scale.is_finite(),
                o,
                "motion_distortion.scale",
                e.scale,
                "must be finite",
            )?;
        }
        if let Some(e) = &self.intensity_noise {
            check(
                e.sigma_rel >= 0.0,
                o,
                "intensity_noise.sigma_rel",
                e.sigma_rel,
                "must be >= 0",
            )?;
        }
        Ok(())
    }

    /// The enabled effects in their physical order: blocking and drop models
    /// first (on ideal features), then atmosphere, edge mixing, range noise,
    /// quantisation, motion (no de-skew) and intensity noise.
    pub fn effects(&self) -> Physics {
        let mut effects: Vec<Box<dyn Effect>> = Vec::new();
        macro_rules! push {
            ($($field:ident),*) => {$(
                if let Some(e) = &self.$field {
                    if e.enabled {
                        effects.push(Box::new(e.clone()));
                    }
                }
            )*};
        }
        push!(
            self_occlusion,
            beam_dropout,
            range_dropout,
            incidence_dropout,
            material_dropout,
            edge_dropout,
            uniform_dropout,
            intensity_dropout,
            atmosphere,
            mixed_pixels,
            range_noise,
            range_quantization,
            motion_distortion,
            intensity_noise
        );
        Physics { effects }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presets_validate_and_round_trip_through_json() {
        for name in Preset::NAMES {
            let c = PhysicsConfig::resolve(name).unwrap();
            c.validate(name, Some(64)).unwrap();
            let back: PhysicsConfig = serde_json::from_str(&c.to_json()).unwrap();
            assert_eq!(back, c);
        }
        assert!(Preset::Ideal.config().effects().is_ideal());
        let vlp16 = PhysicsConfig::resolve_for_beams("realistic", 16).unwrap();
        vlp16.validate("realistic", Some(16)).unwrap();
        assert_eq!(
            vlp16.beam_dropout.and_then(|b| b.rates).map(|r| r.len()),
            Some(16)
        );
        assert_eq!(
            Preset::CarlaLike.config().effects().ids(),
            ["uniform_dropout", "intensity_dropout"]
        );
        let ids = Preset::Realistic.config().effects().ids();
        for id in [
            "self_occlusion",
            "beam_dropout",
            "range_dropout",
            "incidence_dropout",
            "material_dropout",
            "range_noise",
            "mixed_pixels",
            "motion_distortion",
        ] {
            assert!(ids.contains(&id), "realistic lacks {id}");
        }
    }

    #[test]
    fn bad_files_and_parameters_are_named() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("p.json");
        std::fs::write(
            &path,
            r#"{"range_dropout": {"range_50_m": -3, "softness": 0.5}}"#,
        )
        .unwrap();
        let err = PhysicsConfig::load(&path).unwrap_err().to_string();
        assert!(
            err.contains("p.json") && err.contains("range_dropout.range_50_m"),
            "{err}"
        );
        std::fs::write(
            &path,
            r#"{"range_dropout": {"range_50": 3, "softness": 0.5}}"#,
        )
        .unwrap();
        let err = PhysicsConfig::load(&path).unwrap_err().to_string();
        assert!(err.contains("p.json") && err.contains("range_50"), "{err}");
        std::fs::write(&path, r#"{"uniform_dropout": {"prob": 0.2, "enabled": false}, "material_dropout": {"drop_prob": {"glass": 0.5}}}"#).unwrap();
        let c = PhysicsConfig::load(&path).unwrap();
        assert_eq!(c.effects().ids(), ["material_dropout"]);
        let beams = PhysicsConfig {
            beam_dropout: Some(BeamDropout {
                enabled: true,
                rates: Some(vec![0.1; 32]),
                mean_rate: 0.0,
                spread: 0.0,
                beam_seed: 0,
                dead_beams: vec![],
            }),
            ..Default::default()
        };
        assert!(
            beams
                .validate("x", Some(64))
                .unwrap_err()
                .to_string()
                .contains("beam_dropout.rates")
        );
        assert!(
            PhysicsConfig::resolve("foggy")
                .unwrap_err()
                .to_string()
                .contains("carla-like")
        );
    }
    #[test]
    fn edge_bands_start_at_zero_rise_and_stand_alone() {
        let edges = |json: &str| -> Result<(), String> {
            let c: PhysicsConfig = serde_json::from_str(json).map_err(|e| e.to_string())?;
            c.validate("p.json", Some(64)).map_err(|e| e.to_string())
        };
        let band = |from: f32, p: f32| format!(r#"{{"from_m": {from}, "drop_prob_by_px": [{p}]}}"#);
        let banded =
            |bands: &[String]| format!(r#"{{"edge_dropout": {{"bands": [{}]}}}}"#, bands.join(","));
        edges(&banded(&[band(0.0, 0.2), band(20.0, 0.0)])).unwrap();
        edges(r#"{"edge_dropout": {"drop_prob_by_px": [0.3, 0.1]}}"#).unwrap();
        let err = edges(&banded(&[band(5.0, 0.2)])).unwrap_err();
        assert!(err.contains("edge_dropout.bands[0].from_m"), "{err}");
        let err = edges(&banded(&[band(0.0, 0.2), band(20.0, 0.1), band(20.0, 0.0)])).unwrap_err();
        assert!(err.contains("edge_dropout.bands[2].from_m"), "{err}");
        let err = edges(&banded(&[band(0.0, 1.5)])).unwrap_err();
        assert!(
            err.contains("edge_dropout.bands[0].drop_prob_by_px[0]"),
            "{err}"
        );
        let both = r#"{"edge_dropout": {"drop_prob_by_px": [0.3], "bands": [{"from_m": 0, "drop_prob_by_px": [0.2]}]}}"#;
        assert!(edges(both).unwrap_err().contains("not both"));
    }
}
