//! Sensor profiles: which beams a LiDAR has (elevation table, optional per-beam
//! azimuth offsets), how many columns a revolution has, and the valid range.
//! Built-in profiles, JSON profile files (`schemas/sensor_profile.schema.json`)
//! and Ouster metadata JSON all give the same [`SensorProfile`].

use std::f32::consts::PI;
use std::path::Path;

use serde::{Deserialize, Serialize};

use super::AngleGrid;

/// A LiDAR's angular layout and range limits. Row 0 is the top beam.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SensorProfile {
    pub name: String,
    /// Beam elevations in degrees, row 0 (top) first, decreasing.
    pub elevation_deg: Vec<f32>,
    /// Per-beam azimuth offsets in degrees (Ouster `beam_azimuth_angles`), if any.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub azimuth_offset_deg: Option<Vec<f32>>,
    /// Columns per revolution.
    pub columns: usize,
    pub min_range_m: f32,
    pub max_range_m: f32,
}

/// Errors loading a profile; each names the file.
#[derive(Debug, thiserror::Error)]
pub enum ProfileError {
    #[error("unknown sensor profile '{0}' (built in: {names}); or give a profile JSON file", names = SensorProfile::BUILTIN.join(", "))]
    Unknown(String),
    #[error("{path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
    #[error("{path}: {source}")]
    Json {
        path: String,
        source: serde_json::Error,
    },
    #[error("{path}: {reason}")]
    Invalid { path: String, reason: String },
}

/// KITTI's Velodyne HDL-64E: median elevation of each ring over six real KITTI
/// scans (sequence 00, frames 0-5), ring order split at the forward azimuth.
const HDL64E_ELEVATION_DEG: [f32; 64] = [
    2.613, 2.227, 1.995, 1.544, 1.263, 0.833, 0.572, 0.176, -0.161, -0.569, -0.876, -1.219, -1.566,
    -1.868, -2.169, -2.524, -2.836, -3.245, -3.518, -3.912, -4.217, -4.582, -4.894, -5.181, -5.542,
    -5.851, -6.147, -6.411, -6.778, -7.144, -7.382, -7.766, -8.396, -8.911, -9.371, -9.763,
    -10.221, -10.824, -11.321, -11.746, -12.2, -12.625, -13.154, -13.672, -14.241, -14.676,
    -15.173, -15.545, -16.169, -16.694, -17.256, -17.715, -18.211, -18.631, -19.07, -19.627,
    -20.126, -20.786, -21.261, -21.682, -22.109, -22.755, -23.211, -23.742,
];

/// Velodyne VLP-32C beam elevations (datasheet), sorted top first.
const VLP32C_ELEVATION_DEG: [f32; 32] = [
    15.0, 10.333, 7.0, 4.667, 3.333, 2.333, 1.667, 1.333, 1.0, 0.667, 0.333, 0.0, -0.333, -0.667,
    -1.0, -1.333, -1.667, -2.0, -2.333, -2.667, -3.0, -3.333, -3.667, -4.0, -4.667, -5.333, -6.148,
    -7.254, -8.843, -11.31, -15.639, -25.0,
];

/// Hesai Pandar64 beam elevations (the maker's nominal table, as PandaSet uses it), top first:
/// dense (0.17 deg) from +2 to -6 deg.
const PANDAR64_ELEVATION_DEG: [f32; 64] = [
    14.882, 11.032, 8.059, 5.057, 3.04, 2.028, 1.86, 1.688, 1.522, 1.351, 1.184, 1.013, 0.846,
    0.675, 0.508, 0.337, 0.169, 0.0, -0.169, -0.337, -0.508, -0.675, -0.846, -1.013, -1.184,
    -1.351, -1.522, -1.688, -1.86, -2.028, -2.198, -2.365, -2.536, -2.7, -2.873, -3.04, -3.21,
    -3.375, -3.548, -3.712, -3.884, -4.05, -4.221, -4.385, -4.558, -4.72, -4.892, -5.057, -5.229,
    -5.391, -5.565, -5.726, -5.898, -6.061, -7.063, -8.059, -9.06, -9.885, -11.032, -12.006,
    -12.974, -13.93, -18.889, -24.897,
];

/// Velodyne VLS-128 (Alpha Prime) beam elevations (the maker's table, the same as nebula's
/// `VLS128.yaml` calibration), sorted top first.
#[allow(clippy::approx_constant)] // -6.28 deg is a beam, not -tau
const VLS128_ELEVATION_DEG: [f32; 128] = [
    15.0, 11.75, 9.7, 8.43, 7.58, 6.98, 6.48, 6.08, 5.73, 5.43, 5.18, 4.98, 4.83, 4.72, 4.61, 4.5,
    4.39, 4.28, 4.17, 4.06, 3.95, 3.84, 3.73, 3.62, 3.51, 3.4, 3.29, 3.18, 3.07, 2.96, 2.85, 2.74,
    2.63, 2.52, 2.41, 2.3, 2.19, 2.08, 1.97, 1.86, 1.75, 1.64, 1.53, 1.42, 1.31, 1.2, 1.09, 0.98,
    0.87, 0.76, 0.65, 0.54, 0.43, 0.32, 0.21, 0.1, -0.01, -0.12, -0.23, -0.34, -0.45, -0.56, -0.67,
    -0.78, -0.89, -1.0, -1.11, -1.22, -1.33, -1.44, -1.55, -1.66, -1.77, -1.88, -1.99, -2.1, -2.21,
    -2.32, -2.43, -2.54, -2.65, -2.76, -2.87, -2.98, -3.09, -3.2, -3.31, -3.42, -3.53, -3.64,
    -3.75, -3.86, -3.97, -4.08, -4.19, -4.3, -4.41, -4.52, -4.63, -4.74, -4.85, -4.96, -5.07,
    -5.18, -5.29, -5.4, -5.51, -5.62, -5.73, -5.84, -5.95, -6.06, -6.17, -6.28, -6.39, -6.5, -6.65,
    -6.85, -7.15, -7.65, -8.352, -9.244, -10.346, -11.742, -13.565, -16.042, -19.582, -25.0,
];

fn uniform(top_deg: f32, bottom_deg: f32, beams: usize) -> Vec<f32> {
    let step = (top_deg - bottom_deg) / (beams - 1) as f32;
    (0..beams).map(|i| top_deg - step * i as f32).collect()
}

/// Most beams a profile may have (the largest sensors have 128).
pub const MAX_BEAMS: usize = 512;

/// Most columns per revolution (Velodyne at 0.1 deg: 3600; Ouster: 4096 at most).
/// With [`MAX_BEAMS`] this bounds one range image to 8 M pixels.
pub const MAX_COLUMNS: usize = 16_384;

/// Checks a range-image width (`--columns`) before anything is sized by it.
pub fn check_columns(columns: usize) -> Result<(), String> {
    if columns == 0 || columns > MAX_COLUMNS {
        return Err(format!(
            "--columns {columns}: give 1 to {MAX_COLUMNS} columns per revolution"
        ));
    }
    Ok(())
}

impl SensorProfile {
    /// Names accepted by [`SensorProfile::builtin`].
    pub const BUILTIN: [&'static str; 19] = [
        "hdl64e",
        "hdl32e",
        "vlp16",
        "vlp32c",
        "vls128",
        "pandar64",
        "pandarxt32",
        "os0-32",
        "os0-64",
        "os0-128",
        "os1-32",
        "os1-64",
        "os1-128",
        "os1-16-gen1",
        "os1-32-gen1",
        "os1-64-gen1",
        "os2-32",
        "os2-64",
        "os2-128",
    ];

    /// KITTI's HDL-64E at its native ~2048 columns per revolution, 1.45-80 m as in
    /// the reference preprocessing.
    pub fn kitti_hdl64e() -> Self {
        SensorProfile {
            name: "hdl64e".into(),
            elevation_deg: HDL64E_ELEVATION_DEG.to_vec(),
            azimuth_offset_deg: None,
            columns: 2048,
            min_range_m: 1.45,
            max_range_m: 80.0,
        }
    }

    /// A built-in profile by name (case-insensitive; `kitti` is an alias of `hdl64e`).
    pub fn builtin(name: &str) -> Result<Self, ProfileError> {
        let lower = name.to_ascii_lowercase();
        let make = |elevation_deg: Vec<f32>, columns, min_range_m, max_range_m| SensorProfile {
            name: lower.clone(),
            elevation_deg,
            azimuth_offset_deg: None,
            columns,
            min_range_m,
            max_range_m,
        };
        Ok(match lower.as_str() {
            "hdl64e" | "kitti" => Self::kitti_hdl64e(),
            // nuScenes' HDL-32E: +10.67 to -30.67 deg, 1.33 deg apart.
            "hdl32e" => make(uniform(10.67, -30.67, 32), 1084, 0.5, 70.0),
            "vlp16" => make(uniform(15.0, -15.0, 16), 1800, 0.4, 100.0),
            "vlp32c" => make(VLP32C_ELEVATION_DEG.to_vec(), 1800, 0.5, 200.0),
            "vls128" => make(VLS128_ELEVATION_DEG.to_vec(), 1800, 1.0, 245.0),
            "pandar64" => make(PANDAR64_ELEVATION_DEG.to_vec(), 1800, 0.3, 200.0),
            // Hesai PandarXT32: +15 to -16 deg, 1 deg apart, 0.18 deg at 10 Hz.
            "pandarxt32" => make(uniform(15.0, -16.0, 32), 2000, 0.05, 120.0),
            // Ouster, uniform beam spacing as the data sheets give it (a unit's own
            // `beam_altitude_angles`, e.g. a gradient or below-horizon OS1-32, come with its
            // metadata JSON: `--sensor metadata.json`). OS1 gen 2 and later: 45 deg of
            // vertical view; OS1 gen 1: 33.2 deg; OS0: 90 deg; OS2: 22.5 deg.
            "os1-32" => make(uniform(22.5, -22.5, 32), 1024, 0.3, 120.0),
            "os1-64" => make(uniform(22.5, -22.5, 64), 2048, 0.3, 120.0),
            "os1-128" => make(uniform(22.5, -22.5, 128), 2048, 0.3, 120.0),
            "os1-16-gen1" => make(uniform(16.6, -16.6, 16), 1024, 0.3, 120.0),
            "os1-32-gen1" => make(uniform(16.6, -16.6, 32), 1024, 0.3, 120.0),
            "os1-64-gen1" => make(uniform(16.6, -16.6, 64), 2048, 0.3, 120.0),
            "os0-32" => make(uniform(45.0, -45.0, 32), 1024, 0.3, 75.0),
            "os0-64" => make(uniform(45.0, -45.0, 64), 1024, 0.3, 75.0),
            "os0-128" => make(uniform(45.0, -45.0, 128), 1024, 0.3, 75.0),
            "os2-32" => make(uniform(11.25, -11.25, 32), 1024, 0.8, 350.0),
            "os2-64" => make(uniform(11.25, -11.25, 64), 2048, 0.8, 350.0),
            "os2-128" => make(uniform(11.25, -11.25, 128), 2048, 0.8, 350.0),
            _ => return Err(ProfileError::Unknown(name.to_string())),
        })
    }

    /// A built-in name, or else a path to a profile JSON or Ouster metadata JSON.
    pub fn resolve(name_or_path: &str) -> Result<Self, ProfileError> {
        match Self::builtin(name_or_path) {
            Ok(p) => Ok(p),
            Err(e) if !Path::new(name_or_path).exists() => Err(e),
            Err(_) => Self::load(Path::new(name_or_path)),
        }
    }

    /// Loads a profile JSON file, or an Ouster sensor metadata JSON
    /// (`beam_altitude_angles`, `beam_azimuth_angles`, optional `lidar_mode`).
    pub fn load(path: &Path) -> Result<Self, ProfileError> {
        let p = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|source| ProfileError::Io {
            path: p.clone(),
            source,
        })?;
        let value: serde_json::Value =
            serde_json::from_str(&text).map_err(|source| ProfileError::Json {
                path: p.clone(),
                source,
            })?;
        let profile = if let Some(ouster) = find_key(&value, "beam_altitude_angles") {
            Self::from_ouster(&value, ouster, &p)?
        } else {
            serde_json::from_value(value).map_err(|source| ProfileError::Json {
                path: p.clone(),
                source,
            })?
        };
        profile
            .validate()
            .map_err(|reason| ProfileError::Invalid { path: p, reason })?;
        Ok(profile)
    }

    fn from_ouster(
        root: &serde_json::Value,
        altitudes: &serde_json::Value,
        path: &str,
    ) -> Result<Self, ProfileError> {
        let floats = |v: &serde_json::Value| -> Option<Vec<f32>> {
            v.as_array()?
                .iter()
                .map(|x| x.as_f64().map(|f| f as f32))
                .collect()
        };
        let invalid = |reason: &str| ProfileError::Invalid {
            path: path.into(),
            reason: reason.into(),
        };
        let elevation_deg = floats(altitudes)
            .ok_or_else(|| invalid("beam_altitude_angles is not a list of numbers"))?;
        let azimuth_offset_deg = match find_key(root, "beam_azimuth_angles") {
            Some(v) => Some(
                floats(v).ok_or_else(|| invalid("beam_azimuth_angles is not a list of numbers"))?,
            ),
            None => None,
        };
        // lidar_mode looks like "1024x10": columns x frequency; without a readable one,
        // the data format's columns_per_frame says it (`import` reads the same).
        let columns = find_key(root, "lidar_mode")
            .and_then(|m| m.as_str())
            .and_then(|m| m.split('x').next())
            .and_then(|c| c.parse().ok())
            .or_else(|| {
                find_key(root, "columns_per_frame")
                    .and_then(|c| c.as_u64())
                    .map(|c| c as usize)
            })
            .ok_or_else(|| {
                invalid(
                    "neither lidar_mode (e.g. \"1024x10\") nor columns_per_frame gives the columns",
                )
            })?;
        let prod = find_key(root, "prod_line")
            .and_then(|v| v.as_str())
            .unwrap_or("ouster");
        Ok(SensorProfile {
            name: prod.to_ascii_lowercase(),
            elevation_deg,
            azimuth_offset_deg,
            columns,
            min_range_m: 0.3,
            max_range_m: 120.0,
        })
    }

    /// Checks the invariants the projection relies on, including the size limits
    /// that keep a range image's memory bounded.
    pub fn validate(&self) -> Result<(), String> {
        if self.elevation_deg.is_empty() {
            return Err("no beams".into());
        }
        if self.elevation_deg.len() > MAX_BEAMS {
            return Err(format!(
                "{} beams; at most {MAX_BEAMS} are supported",
                self.elevation_deg.len()
            ));
        }
        check_columns(self.columns)?;
        if let Some(off) = &self.azimuth_offset_deg
            && off.len() != self.elevation_deg.len()
        {
            return Err(format!(
                "{} azimuth offsets for {} beams",
                off.len(),
                self.elevation_deg.len()
            ));
        }
        if !(self.min_range_m >= 0.0 && self.max_range_m > self.min_range_m) {
            return Err(format!(
                "range {}..{} m is empty",
                self.min_range_m, self.max_range_m
            ));
        }
        let max = crate::lidar::scan::MAX_RETURN_RANGE_M;
        if self.max_range_m > max {
            return Err(format!(
                "max_range_m {} is beyond {max} m, farther than any LiDAR measures",
                self.max_range_m
            ));
        }
        if let Some(e) = (self.elevation_deg.iter()).find(|e| !(-90.0..=90.0).contains(*e)) {
            return Err(format!("elevation {e} deg is outside -90..90 deg"));
        }
        // Rows are beams top first: a table in another order would put every row at another
        // beam's elevation.
        let e = &self.elevation_deg;
        if let Some(i) = (1..e.len()).find(|&i| e[i] > e[i - 1]) {
            return Err(format!(
                "elevation_deg must list the beams top first, but beam {i} ({} deg) is above \
                 beam {} ({} deg); order the beams from the highest to the lowest, with their \
                 azimuth offsets in the same order",
                e[i],
                i - 1,
                e[i - 1]
            ));
        }
        if let Some(off) = &self.azimuth_offset_deg
            && let Some(a) = off.iter().find(|a| !(-360.0..=360.0).contains(*a))
        {
            return Err(format!("azimuth offset {a} deg is outside -360..360 deg"));
        }
        Ok(())
    }

    /// The same sensor with another number of columns per revolution.
    pub fn with_columns(mut self, columns: usize) -> Self {
        self.columns = columns;
        self
    }

    /// Beams (rows of the range image).
    pub fn beams(&self) -> usize {
        self.elevation_deg.len()
    }

    /// The per-pixel angle grid of this profile (see [`AngleGrid`]): rows at the beam
    /// elevations, columns at `pi - (j + 0.5) * 2 pi / W`. Points are binned by their
    /// measured azimuth, so per-beam azimuth offsets do not move a pixel's direction.
    pub fn angle_grid(&self) -> AngleGrid {
        AngleGrid::regular_columns(self.beams(), self.columns, |i| {
            self.elevation_deg[i].to_radians()
        })
    }
}

/// Wraps an angle to (-pi, pi].
pub fn wrap_pi(a: f32) -> f32 {
    let mut a = (a + PI).rem_euclid(2.0 * PI) - PI;
    if a <= -PI {
        a += 2.0 * PI;
    }
    a
}

/// Looks for `key` at the top level or one object down (Ouster nests it under
/// `beam_intrinsics` in newer metadata).
fn find_key<'a>(v: &'a serde_json::Value, key: &str) -> Option<&'a serde_json::Value> {
    let obj = v.as_object()?;
    obj.get(key)
        .or_else(|| obj.values().find_map(|child| child.as_object()?.get(key)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn builtins_are_valid_and_ordered_top_down() {
        for name in SensorProfile::BUILTIN {
            let p = SensorProfile::builtin(name).unwrap();
            p.validate().unwrap();
            assert!(
                p.elevation_deg.windows(2).all(|w| w[0] > w[1]),
                "{name} not sorted top-down"
            );
        }
        assert_eq!(SensorProfile::builtin("KITTI").unwrap().beams(), 64);
        let err = SensorProfile::builtin("hdl65").unwrap_err().to_string();
        assert!(err.contains("hdl65") && err.contains("vlp16"), "{err}");
    }

    #[test]
    fn a_table_that_is_not_top_first_is_refused_by_file_and_field() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("bottom_first.json");
        let mut p = SensorProfile::builtin("vlp16").unwrap();
        p.elevation_deg.reverse();
        std::fs::write(&path, serde_json::to_string(&p).unwrap()).unwrap();
        let err = SensorProfile::load(&path).unwrap_err().to_string();
        assert!(
            err.contains("bottom_first.json")
                && err.contains("elevation_deg")
                && err.contains("top first"),
            "{err}"
        );
    }

    #[test]
    fn ouster_metadata_without_a_lidar_mode_takes_its_columns_per_frame() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("meta.json");
        let beams: Vec<f32> = (0..16).map(|i| 15.0 - 2.0 * i as f32).collect();
        let meta = serde_json::json!({
            "beam_altitude_angles": beams,
            "lidar_mode": "unparsable",
            "data_format": { "columns_per_frame": 2048 },
        });
        std::fs::write(&path, meta.to_string()).unwrap();
        assert_eq!(SensorProfile::load(&path).unwrap().columns, 2048);
        let meta = serde_json::json!({ "beam_altitude_angles": beams });
        std::fs::write(&path, meta.to_string()).unwrap();
        let err = SensorProfile::load(&path).unwrap_err().to_string();
        assert!(
            err.contains("meta.json") && err.contains("columns_per_frame"),
            "{err}"
        );
    }

    #[test]
    fn profile_json_round_trips() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("p.json");
        let p = SensorProfile::builtin("vlp16").unwrap().with_columns(900);
        std::fs::write(&path, serde_json::to_string(&p).unwrap()).unwrap();
        assert_eq!(SensorProfile::resolve(path.to_str().unwrap()).unwrap(), p);
    }

    #[test]
    fn loads_real_ouster_metadata() {
        let path = Path::new("../shared/real_lidar/ouster/OS-1-32-G_v2.1.1_1024x10.json");
        if !path.exists() {
            eprintln!(
                "skipped: {} is absent (real data lives beside the repo)",
                path.display()
            );
            return;
        }
        let p = SensorProfile::load(path).unwrap();
        assert_eq!(p.beams(), 32);
        assert_eq!(p.columns, 1024);
        assert_eq!(p.azimuth_offset_deg.as_ref().map(Vec::len), Some(32));
        assert!(p.elevation_deg[0] > p.elevation_deg[31]);
    }

    #[test]
    fn column_azimuths_follow_the_reference_convention() {
        let g = SensorProfile::kitti_hdl64e().with_columns(4).angle_grid();
        // Column 0 at the rear (just below +pi), clockwise.
        let expect = [0.75 * PI, 0.25 * PI, -0.25 * PI, -0.75 * PI];
        for (j, e) in expect.iter().enumerate() {
            assert!((g.azimuth_rad[j] - e).abs() < 1e-6);
        }
        assert!((wrap_pi(3.0 * PI / 2.0) + PI / 2.0).abs() < 1e-6);
    }

    #[test]
    fn profile_json_matches_its_schema() {
        let schema: serde_json::Value =
            serde_json::from_str(include_str!("../../schemas/sensor_profile.schema.json")).unwrap();
        let props = schema["properties"].as_object().unwrap();
        let required: Vec<&str> = schema["required"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_str().unwrap())
            .collect();
        let ouster = SensorProfile {
            azimuth_offset_deg: Some(vec![0.0; 64]),
            ..SensorProfile::builtin("os1-64").unwrap()
        };
        for p in SensorProfile::BUILTIN
            .iter()
            .map(|n| SensorProfile::builtin(n).unwrap())
            .chain([ouster])
        {
            let v = serde_json::to_value(&p).unwrap();
            let obj = v.as_object().unwrap();
            for key in obj.keys() {
                assert!(
                    props.contains_key(key),
                    "{key} is written but not in the schema"
                );
            }
            for key in &required {
                assert!(
                    obj.contains_key(*key),
                    "{key} is required by the schema but not written"
                );
            }
        }
        let example: SensorProfile = serde_json::from_value(schema["examples"][0].clone()).unwrap();
        assert_eq!(
            example,
            SensorProfile {
                name: "vlp16".into(),
                ..SensorProfile::builtin("vlp16").unwrap()
            }
        );
    }
}
