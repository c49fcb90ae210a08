//! Sensor metadata (`*.json`) parsing for both Ouster metadata layouts.
//!
//! Older firmware and SDKs wrote a *legacy flat* file (beam intrinsics at
//! the top level, packet layout under `data_format`); newer ones write a
//! *nested* file (`beam_intrinsics`, `lidar_intrinsics`, `lidar_data_format`,
//! `config_params`, `sensor_info`). Each field is looked up under every path
//! it is known to live at, nested first, so both layouts (and hand-edited
//! mixtures of them) parse the same way.

use serde_json::Value;

use super::OusterError;

/// Largest `columns_per_frame` any Ouster lidar mode uses (4096x5).
const MAX_COLUMNS_PER_FRAME: usize = 4096;
/// Largest beam count of any Ouster sensor (128); a little headroom.
const MAX_PIXELS_PER_COLUMN: usize = 256;
/// UDP datagrams cannot exceed this, so no valid format may either.
const MAX_UDP_PAYLOAD: usize = 65_507;

/// Lidar UDP packet profile (`udp_profile_lidar`); selects the byte layout.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum UdpProfile {
    /// Pre-2.2 fixed layout: 16-byte column header, 12-byte pixels, 4-byte
    /// column footer, no packet header/footer.
    Legacy,
    /// `RNG19_RFL8_SIG16_NIR16`: single return, 12-byte pixels.
    Rng19Rfl8Sig16Nir16,
    /// `RNG15_RFL8_NIR8`: "low bandwidth", 4-byte pixels, range in 8 mm units.
    Rng15Rfl8Nir8,
    /// `RNG19_RFL8_SIG16_NIR16_DUAL`: two returns, 16-byte pixels; only the
    /// first return (`RANGE`, not `RANGE2`) is decoded.
    Rng19Rfl8Sig16Nir16Dual,
}

impl UdpProfile {
    /// Parses the metadata spelling; absent means LEGACY per Ouster's docs.
    pub fn from_name(name: &str) -> Result<Self, OusterError> {
        match name {
            "LEGACY" => Ok(Self::Legacy),
            "RNG19_RFL8_SIG16_NIR16" => Ok(Self::Rng19Rfl8Sig16Nir16),
            "RNG15_RFL8_NIR8" => Ok(Self::Rng15Rfl8Nir8),
            "RNG19_RFL8_SIG16_NIR16_DUAL" => Ok(Self::Rng19Rfl8Sig16Nir16Dual),
            other => Err(meta_err(format!(
                "unsupported udp_profile_lidar {other:?} (supported: LEGACY, \
                 RNG19_RFL8_SIG16_NIR16, RNG15_RFL8_NIR8, RNG19_RFL8_SIG16_NIR16_DUAL)"
            ))),
        }
    }

    /// The metadata spelling, used in error messages.
    pub fn name(self) -> &'static str {
        match self {
            Self::Legacy => "LEGACY",
            Self::Rng19Rfl8Sig16Nir16 => "RNG19_RFL8_SIG16_NIR16",
            Self::Rng15Rfl8Nir8 => "RNG15_RFL8_NIR8",
            Self::Rng19Rfl8Sig16Nir16Dual => "RNG19_RFL8_SIG16_NIR16_DUAL",
        }
    }

    /// Bytes of one pixel (one beam of one column).
    pub fn bytes_per_pixel(self) -> usize {
        match self {
            Self::Legacy | Self::Rng19Rfl8Sig16Nir16 => 12,
            Self::Rng15Rfl8Nir8 => 4,
            Self::Rng19Rfl8Sig16Nir16Dual => 16,
        }
    }

    /// (packet header, column header, column footer, packet footer) sizes.
    pub(crate) fn framing(self) -> (usize, usize, usize, usize) {
        match self {
            Self::Legacy => (0, 16, 4, 0),
            _ => (32, 12, 0, 32),
        }
    }
}

/// What the decoder needs from an Ouster metadata JSON file.
#[derive(Debug, Clone, PartialEq)]
pub struct OusterMetadata {
    /// Elevation of each beam in degrees, row 0 first (the top beam).
    pub beam_altitude_angles: Vec<f64>,
    /// Azimuth offset of each beam in degrees.
    pub beam_azimuth_angles: Vec<f64>,
    /// Radial distance from the lidar origin to the beam origin (mm); this
    /// is `beam_to_lidar_transform[0][3]` when that matrix is given.
    pub lidar_origin_to_beam_origin_mm: f64,
    /// Vertical beam-origin offset (`beam_to_lidar_transform[2][3]`, mm);
    /// zero on OS sensors, non-zero on some newer models.
    pub beam_origin_z_mm: f64,
    /// Lidar frame to sensor frame, 4x4 row-major, translation in mm.
    pub lidar_to_sensor_transform: [f64; 16],
    /// E.g. `"1024x10"`, when the file states it.
    pub lidar_mode: Option<String>,
    pub columns_per_frame: usize,
    pub columns_per_packet: usize,
    pub pixels_per_column: usize,
    /// Per-row destagger shift in columns (see the module docs).
    pub pixel_shift_by_row: Vec<i32>,
    /// Destination UDP port of lidar packets; 0 means "any port".
    pub udp_port_lidar: u16,
    pub udp_profile_lidar: UdpProfile,
}

fn meta_err(msg: String) -> OusterError {
    OusterError::Metadata(msg)
}

/// Returns the first value found under any of `paths` (each a key chain).
fn lookup<'a>(root: &'a Value, paths: &[&[&str]]) -> Option<&'a Value> {
    paths.iter().find_map(|path| {
        path.iter()
            .try_fold(root, |v, key| v.get(key))
            .filter(|v| !v.is_null())
    })
}

fn describe(paths: &[&[&str]]) -> String {
    paths
        .iter()
        .map(|p| p.join("."))
        .collect::<Vec<_>>()
        .join(" or ")
}

fn f64_array(root: &Value, paths: &[&[&str]]) -> Result<Option<Vec<f64>>, OusterError> {
    let Some(value) = lookup(root, paths) else {
        return Ok(None);
    };
    let bad = || {
        meta_err(format!(
            "{} must be a flat array of numbers (per-pixel angle tables are not supported)",
            describe(paths)
        ))
    };
    let items = value.as_array().ok_or_else(bad)?;
    let out: Option<Vec<f64>> = items.iter().map(Value::as_f64).collect();
    out.map(Some).ok_or_else(bad)
}

fn required_f64_array(root: &Value, paths: &[&[&str]]) -> Result<Vec<f64>, OusterError> {
    f64_array(root, paths)?.ok_or_else(|| meta_err(format!("missing {}", describe(paths))))
}

fn f64_field(root: &Value, paths: &[&[&str]]) -> Result<Option<f64>, OusterError> {
    lookup(root, paths)
        .map(|v| {
            v.as_f64()
                .ok_or_else(|| meta_err(format!("{} must be a number", describe(paths))))
        })
        .transpose()
}

fn usize_field(root: &Value, paths: &[&[&str]]) -> Result<Option<usize>, OusterError> {
    lookup(root, paths)
        .map(|v| {
            v.as_u64()
                .and_then(|n| usize::try_from(n).ok())
                .ok_or_else(|| {
                    meta_err(format!(
                        "{} must be a non-negative integer",
                        describe(paths)
                    ))
                })
        })
        .transpose()
}

fn str_field<'a>(root: &'a Value, paths: &[&[&str]]) -> Result<Option<&'a str>, OusterError> {
    lookup(root, paths)
        .map(|v| {
            v.as_str()
                .ok_or_else(|| meta_err(format!("{} must be a string", describe(paths))))
        })
        .transpose()
}

const ALTITUDE: &[&[&str]] = &[
    &["beam_intrinsics", "beam_altitude_angles"],
    &["beam_altitude_angles"],
];
const AZIMUTH: &[&[&str]] = &[
    &["beam_intrinsics", "beam_azimuth_angles"],
    &["beam_azimuth_angles"],
];
const BEAM_ORIGIN: &[&[&str]] = &[
    &["beam_intrinsics", "lidar_origin_to_beam_origin_mm"],
    &["lidar_origin_to_beam_origin_mm"],
];
const BEAM_TO_LIDAR: &[&[&str]] = &[
    &["beam_intrinsics", "beam_to_lidar_transform"],
    &["beam_to_lidar_transform"],
];
const LIDAR_TO_SENSOR: &[&[&str]] = &[
    &["lidar_intrinsics", "lidar_to_sensor_transform"],
    &["lidar_to_sensor_transform"],
];
const LIDAR_MODE: &[&[&str]] = &[&["config_params", "lidar_mode"], &["lidar_mode"]];
const UDP_PORT: &[&[&str]] = &[&["config_params", "udp_port_lidar"], &["udp_port_lidar"]];
const COLUMNS_PER_FRAME: &[&[&str]] = &[
    &["lidar_data_format", "columns_per_frame"],
    &["data_format", "columns_per_frame"],
];
const COLUMNS_PER_PACKET: &[&[&str]] = &[
    &["lidar_data_format", "columns_per_packet"],
    &["data_format", "columns_per_packet"],
    &["config_params", "columns_per_packet"],
];
const PIXELS_PER_COLUMN: &[&[&str]] = &[
    &["lidar_data_format", "pixels_per_column"],
    &["data_format", "pixels_per_column"],
];
const PIXEL_SHIFT: &[&[&str]] = &[
    &["lidar_data_format", "pixel_shift_by_row"],
    &["data_format", "pixel_shift_by_row"],
];
const PROFILE: &[&[&str]] = &[
    &["lidar_data_format", "udp_profile_lidar"],
    &["data_format", "udp_profile_lidar"],
    &["config_params", "udp_profile_lidar"],
    &["udp_profile_lidar"],
];

/// Columns from a lidar mode such as `"1024x10"` (the number before `x`).
fn columns_of_mode(mode: &str) -> Option<usize> {
    mode.split_once('x')?.0.trim().parse().ok()
}

/// Shifts derived from beam azimuths when `pixel_shift_by_row` is absent
/// (old metadata): a beam with azimuth `a` degrees sees at measurement `m`
/// what an `a = 0` beam sees at `m + a * W / 360`, so it is shifted by that
/// many columns. Offsetting so the smallest shift is 0 reproduces the
/// published tables (checked on a real OS-1-128 file); any constant offset
/// would only rotate the whole image.
fn shifts_from_azimuths(azimuths: &[f64], columns: usize) -> Vec<i32> {
    let min = azimuths.iter().copied().fold(f64::INFINITY, f64::min);
    azimuths
        .iter()
        .map(|a| ((a - min) * columns as f64 / 360.0).round() as i32)
        .collect()
}

impl OusterMetadata {
    /// Parses legacy-flat or nested metadata JSON and validates that the
    /// arrays agree with each other, so the decoder can index without checks.
    pub fn from_json(text: &str) -> Result<Self, OusterError> {
        let root: Value = serde_json::from_str(text)?;
        if !root.is_object() {
            return Err(meta_err("top level must be a JSON object".into()));
        }
        let beam_altitude_angles = required_f64_array(&root, ALTITUDE)?;
        let beam_azimuth_angles = required_f64_array(&root, AZIMUTH)?;
        let (lidar_origin_to_beam_origin_mm, beam_origin_z_mm) = beam_origin(&root)?;
        let lidar_to_sensor_transform = transform16(&root, LIDAR_TO_SENSOR)?
            .ok_or_else(|| meta_err(format!("missing {}", describe(LIDAR_TO_SENSOR))))?;
        let lidar_mode = str_field(&root, LIDAR_MODE)?.map(str::to_owned);
        let columns_per_frame = columns_per_frame(&root, lidar_mode.as_deref())?;
        let pixels_per_column =
            usize_field(&root, PIXELS_PER_COLUMN)?.unwrap_or(beam_altitude_angles.len());
        let pixel_shift_by_row = match lookup(&root, PIXEL_SHIFT) {
            Some(_) => int_array(&root, PIXEL_SHIFT)?,
            None => shifts_from_azimuths(&beam_azimuth_angles, columns_per_frame),
        };
        let udp_port_lidar = match usize_field(&root, UDP_PORT)? {
            None => 7502,
            Some(p) => u16::try_from(p)
                .map_err(|_| meta_err(format!("udp_port_lidar {p} is not a port")))?,
        };
        let udp_profile_lidar = match str_field(&root, PROFILE)? {
            None => UdpProfile::Legacy,
            Some(name) => UdpProfile::from_name(name)?,
        };
        let meta = Self {
            beam_altitude_angles,
            beam_azimuth_angles,
            lidar_origin_to_beam_origin_mm,
            beam_origin_z_mm,
            lidar_to_sensor_transform,
            lidar_mode,
            columns_per_frame,
            columns_per_packet: usize_field(&root, COLUMNS_PER_PACKET)?.unwrap_or(16),
            pixels_per_column,
            pixel_shift_by_row,
            udp_port_lidar,
            udp_profile_lidar,
        };
        meta.validate()?;
        Ok(meta)
    }

    /// Exact UDP payload size of one lidar packet for this format.
    pub fn lidar_packet_size(&self) -> usize {
        let (ph, ch, cf, pf) = self.udp_profile_lidar.framing();
        let col = ch + self.pixels_per_column * self.udp_profile_lidar.bytes_per_pixel() + cf;
        ph + self.columns_per_packet * col + pf
    }

    /// Rejects inconsistent or absurd metadata up front; decoding relies on
    /// these invariants (array lengths, non-zero sizes, bounds). Called by
    /// [`Self::from_json`] and again by the decoder, since fields are public.
    pub fn validate(&self) -> Result<(), OusterError> {
        let h = self.pixels_per_column;
        if h == 0 || h > MAX_PIXELS_PER_COLUMN {
            return Err(meta_err(format!("pixels_per_column {h} out of range")));
        }
        let w = self.columns_per_frame;
        if w == 0 || w > MAX_COLUMNS_PER_FRAME {
            return Err(meta_err(format!("columns_per_frame {w} out of range")));
        }
        let cpp = self.columns_per_packet;
        if cpp == 0 || cpp > w {
            return Err(meta_err(format!("columns_per_packet {cpp} out of range")));
        }
        for (name, len) in [
            ("beam_altitude_angles", self.beam_altitude_angles.len()),
            ("beam_azimuth_angles", self.beam_azimuth_angles.len()),
            ("pixel_shift_by_row", self.pixel_shift_by_row.len()),
        ] {
            if len != h {
                return Err(meta_err(format!(
                    "{name} has {len} entries but pixels_per_column is {h}"
                )));
            }
        }
        if self.lidar_packet_size() > MAX_UDP_PAYLOAD {
            return Err(meta_err(format!(
                "lidar packet size {} exceeds the UDP limit",
                self.lidar_packet_size()
            )));
        }
        self.validate_geometry()
    }

    /// Angles and offsets a sensor can have: beam elevations within +-90 deg, azimuth
    /// offsets within +-180 deg, beam origins within a metre of the lidar's axis, a finite
    /// lidar-to-sensor transform. Anything else would give garbage points, not an error.
    fn validate_geometry(&self) -> Result<(), OusterError> {
        let within = |name: &str, values: &[f64], limit: f64, unit: &str| match values
            .iter()
            .position(|v| !v.is_finite() || v.abs() > limit)
        {
            Some(i) => Err(meta_err(format!(
                "{name}[{i}] is {}{unit}, outside +-{limit}{unit}",
                values[i]
            ))),
            None => Ok(()),
        };
        within(
            "beam_altitude_angles",
            &self.beam_altitude_angles,
            90.0,
            " deg",
        )?;
        within(
            "beam_azimuth_angles",
            &self.beam_azimuth_angles,
            180.0,
            " deg",
        )?;
        within(
            "lidar_origin_to_beam_origin_mm",
            &[self.lidar_origin_to_beam_origin_mm],
            1000.0,
            " mm",
        )?;
        within("beam_origin_z_mm", &[self.beam_origin_z_mm], 1000.0, " mm")?;
        // Translations in mm; rotations within +-1.
        within(
            "lidar_to_sensor_transform",
            &self.lidar_to_sensor_transform,
            1e5,
            "",
        )
    }
}

/// Beam origin offsets (x, z) in mm. `beam_to_lidar_transform` wins when
/// present because it is the newer, more general description.
fn beam_origin(root: &Value) -> Result<(f64, f64), OusterError> {
    if let Some(m) = transform16(root, BEAM_TO_LIDAR)? {
        return Ok((m[3], m[11]));
    }
    let n = f64_field(root, BEAM_ORIGIN)?
        .ok_or_else(|| meta_err(format!("missing {}", describe(BEAM_ORIGIN))))?;
    Ok((n, 0.0))
}

fn transform16(root: &Value, paths: &[&[&str]]) -> Result<Option<[f64; 16]>, OusterError> {
    let Some(values) = f64_array(root, paths)? else {
        return Ok(None);
    };
    let arr: [f64; 16] = values.try_into().map_err(|v: Vec<f64>| {
        meta_err(format!(
            "{} must have 16 entries, has {}",
            describe(paths),
            v.len()
        ))
    })?;
    Ok(Some(arr))
}

fn columns_per_frame(root: &Value, mode: Option<&str>) -> Result<usize, OusterError> {
    if let Some(w) = usize_field(root, COLUMNS_PER_FRAME)? {
        return Ok(w);
    }
    let mode = mode.ok_or_else(|| {
        meta_err("missing columns_per_frame and lidar_mode; cannot size the frame".into())
    })?;
    columns_of_mode(mode).ok_or_else(|| meta_err(format!("cannot parse lidar_mode {mode:?}")))
}

fn int_array(root: &Value, paths: &[&[&str]]) -> Result<Vec<i32>, OusterError> {
    let bad = || meta_err(format!("{} must be an array of integers", describe(paths)));
    let items = lookup(root, paths)
        .and_then(Value::as_array)
        .ok_or_else(bad)?;
    items
        .iter()
        .map(|v| {
            v.as_i64()
                .and_then(|n| i32::try_from(n).ok())
                .ok_or_else(bad)
        })
        .collect()
}
