//! The point-cloud layout shared by ROS `PointCloud2` and `foxglove.PointCloud`:
//! named fields at byte offsets inside a fixed-size point record. Decodes any such
//! layout into a [`Scan`] and packs a [`Scan`] (plus extra float channels) back.

use crate::lidar::Scan;
use crate::lidar::scan::ring_ids;

/// A field's numeric type. ROS `PointField` and Foxglove `NumericType` number the
/// integer types differently; [`Numeric::from_ros`] / [`Numeric::from_foxglove`]
/// translate each.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Numeric {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Numeric {
    const ROS: [Numeric; 8] = [
        Numeric::I8,
        Numeric::U8,
        Numeric::I16,
        Numeric::U16,
        Numeric::I32,
        Numeric::U32,
        Numeric::F32,
        Numeric::F64,
    ];
    const FOXGLOVE: [Numeric; 8] = [
        Numeric::U8,
        Numeric::I8,
        Numeric::U16,
        Numeric::I16,
        Numeric::U32,
        Numeric::I32,
        Numeric::F32,
        Numeric::F64,
    ];

    /// `sensor_msgs/PointField` datatype: INT8=1, UINT8=2, INT16=3, UINT16=4, INT32=5,
    /// UINT32=6, FLOAT32=7, FLOAT64=8.
    pub fn from_ros(code: u8) -> Option<Self> {
        Self::ROS.get((code as usize).checked_sub(1)?).copied()
    }

    /// `foxglove.PackedElementField.NumericType`: UINT8=1, INT8=2, UINT16=3, INT16=4,
    /// UINT32=5, INT32=6, FLOAT32=7, FLOAT64=8.
    pub fn from_foxglove(code: i32) -> Option<Self> {
        Self::FOXGLOVE
            .get(usize::try_from(code).ok()?.checked_sub(1)?)
            .copied()
    }

    pub fn ros_code(self) -> u8 {
        Self::ROS
            .iter()
            .position(|n| *n == self)
            .map_or(0, |p| p as u8 + 1)
    }

    pub fn foxglove_code(self) -> i32 {
        Self::FOXGLOVE
            .iter()
            .position(|n| *n == self)
            .map_or(0, |p| p as i32 + 1)
    }

    pub fn size(self) -> usize {
        match self {
            Numeric::I8 | Numeric::U8 => 1,
            Numeric::I16 | Numeric::U16 => 2,
            Numeric::I32 | Numeric::U32 | Numeric::F32 => 4,
            Numeric::F64 => 8,
        }
    }

    pub fn is_float(self) -> bool {
        matches!(self, Numeric::F32 | Numeric::F64)
    }

    /// Reads one value at the start of `b` (which holds at least `size()` bytes).
    fn read(self, b: &[u8], big_endian: bool) -> f64 {
        macro_rules! get {
            ($t:ty, $n:expr) => {{
                let mut a = [0u8; $n];
                a.copy_from_slice(&b[..$n]);
                if big_endian {
                    <$t>::from_be_bytes(a)
                } else {
                    <$t>::from_le_bytes(a)
                }
            }};
        }
        match self {
            Numeric::I8 => b[0] as i8 as f64,
            Numeric::U8 => b[0] as f64,
            Numeric::I16 => get!(i16, 2) as f64,
            Numeric::U16 => get!(u16, 2) as f64,
            Numeric::I32 => get!(i32, 4) as f64,
            Numeric::U32 => get!(u32, 4) as f64,
            Numeric::F32 => get!(f32, 4) as f64,
            Numeric::F64 => get!(f64, 8),
        }
    }
}

/// One named field of a point record.
#[derive(Debug, Clone, PartialEq)]
pub struct Field {
    pub name: String,
    pub offset: u32,
    pub numeric: Numeric,
    pub count: u32,
}

/// The layout of a point-cloud message's `data`.
#[derive(Debug, Clone, PartialEq)]
pub struct CloudLayout {
    pub fields: Vec<Field>,
    pub point_step: u32,
    pub row_step: u32,
    pub height: u32,
    pub width: u32,
    pub big_endian: bool,
}

/// Why a point-cloud message cannot become a scan. The message is then copied
/// through unchanged and reported.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CloudError {
    #[error("no \"{missing}\" field (found: {found}); pick a channel with --topic")]
    MissingField {
        missing: &'static str,
        found: String,
    },
    #[error("field \"{name}\" has unknown datatype {code}")]
    UnknownDatatype { name: String, code: i32 },
    #[error("field \"{name}\" ends at byte {end}, beyond the {point_step}-byte point")]
    FieldOutsidePoint {
        name: String,
        end: u64,
        point_step: u32,
    },
    #[error("data holds {len} bytes, but height {height} x row_step {row_step} needs {need}")]
    DataTooShort {
        len: usize,
        height: u32,
        row_step: u32,
        need: u64,
    },
    #[error("row_step {row_step} is smaller than width {width} x point_step {point_step}")]
    RowStep {
        row_step: u32,
        width: u32,
        point_step: u32,
    },
    #[error("{0}")]
    Wire(#[from] super::wire::WireError),
    #[error("{0}")]
    Other(String),
}

const INTENSITY: [&str; 4] = ["intensity", "reflectivity", "i", "reflectance"];
const RING: [&str; 4] = ["ring", "channel", "laser_id", "ring_id"];
const TIME: [&str; 5] = ["time", "t", "timestamp", "time_stamp", "time_offset"];
const LABEL: [&str; 2] = ["label", "semantic_label"];

impl CloudLayout {
    fn find(&self, names: &[&str]) -> Option<&Field> {
        names
            .iter()
            .find_map(|n| self.fields.iter().find(|f| f.name == *n))
    }

    fn check(&self, data_len: usize) -> Result<(), CloudError> {
        for f in &self.fields {
            let end = f.offset as u64 + f.numeric.size() as u64 * f.count.max(1) as u64;
            if end > self.point_step as u64 {
                return Err(CloudError::FieldOutsidePoint {
                    name: f.name.clone(),
                    end,
                    point_step: self.point_step,
                });
            }
        }
        if (self.row_step as u64) < self.width as u64 * self.point_step as u64 {
            return Err(CloudError::RowStep {
                row_step: self.row_step,
                width: self.width,
                point_step: self.point_step,
            });
        }
        let need = self.height as u64 * self.row_step as u64;
        if (data_len as u64) < need {
            return Err(CloudError::DataTooShort {
                len: data_len,
                height: self.height,
                row_step: self.row_step,
                need,
            });
        }
        Ok(())
    }

    /// Decodes `data` laid out as `self` into a scan. Integer time fields are taken as
    /// nanoseconds (Ouster `t`), float ones as seconds. Also returns notes on what was read
    /// differently from the message's word (a ring field that could not be used, points too
    /// far to be returns, bytes past the last point), for the caller to report.
    pub fn decode(&self, data: &[u8]) -> Result<(Scan, Vec<String>), CloudError> {
        let found = || {
            self.fields
                .iter()
                .map(|f| f.name.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        };
        let coord = |name: &'static str| {
            self.find(&[name]).ok_or_else(|| CloudError::MissingField {
                missing: name,
                found: found(),
            })
        };
        let (fx, fy, fz) = (coord("x")?, coord("y")?, coord("z")?);
        self.check(data.len())?;
        let n = self.height as usize * self.width as usize;
        let (step, row_step, w) = (
            self.point_step as usize,
            self.row_step as usize,
            self.width as usize,
        );
        let be = self.big_endian;
        let value = |f: &Field, p: &[u8]| f.numeric.read(&p[f.offset as usize..], be);
        let record = |i: usize| {
            let start = (i / w) * row_step + (i % w) * step;
            &data[start..start + step]
        };
        let column = |f: Option<&Field>, scale: f64| -> Option<Vec<f32>> {
            f.map(|f| {
                (0..n)
                    .map(|i| (value(f, record(i)) * scale) as f32)
                    .collect()
            })
        };
        let xyz = (0..n)
            .map(|i| {
                let p = record(i);
                [
                    value(fx, p) as f32,
                    value(fy, p) as f32,
                    value(fz, p) as f32,
                ]
            })
            .collect();
        let time = self.find(&TIME);
        let time_scale = if time.is_some_and(|f| f.numeric.is_float()) {
            1.0
        } else {
            1e-9
        };
        let mut scan = Scan {
            xyz,
            intensity: column(self.find(&INTENSITY), 1.0),
            ring: None,
            time_s: column(time, time_scale),
            label: self
                .find(&LABEL)
                .map(|f| (0..n).map(|i| value(f, record(i)) as u32).collect()),
            height: self.height as usize,
            width: self.width as usize,
        };
        let mut notes = Vec::new();
        if let Some(f) = self.find(&RING) {
            let values: Vec<f64> = (0..n).map(|i| value(f, record(i))).collect();
            match ring_ids(&values, |i| scan.is_return(i)) {
                Ok(ids) => scan.ring = Some(ids),
                Err(bad) => notes.push(format!(
                    "ring field \"{}\" holds {bad} non-finite values at returns; rows taken from the cloud's order or elevation instead",
                    f.name
                )),
            }
        }
        let absurd = scan.absurd_points();
        if absurd > 0 {
            notes.push(format!(
                "{absurd} points lie beyond {} m or overflow; they are not taken as returns",
                crate::lidar::scan::MAX_RETURN_RANGE_M
            ));
        }
        let extra = data.len() as u64 - self.height as u64 * self.row_step as u64;
        if extra > 0 {
            notes.push(format!(
                "{extra} bytes after the last point ignored (data holds {}, height x row_step is {})",
                data.len(),
                self.height as u64 * self.row_step as u64
            ));
        }
        Ok((scan, notes))
    }
}

/// Packs a scan's fields (x, y, z, then intensity, ring, time, label where present,
/// then `extra` float channels) as little-endian records.
pub fn encode(scan: &Scan, extra: &[(&str, &[f32])]) -> (CloudLayout, Vec<u8>) {
    let mut fields = Vec::new();
    let mut offset = 0u32;
    let mut add = |name: &str, numeric: Numeric| {
        fields.push(Field {
            name: name.into(),
            offset,
            numeric,
            count: 1,
        });
        offset += numeric.size() as u32;
    };
    for name in ["x", "y", "z"] {
        add(name, Numeric::F32);
    }
    if scan.intensity.is_some() {
        add("intensity", Numeric::F32);
    }
    if scan.ring.is_some() {
        add("ring", Numeric::U16);
    }
    if scan.time_s.is_some() {
        add("time", Numeric::F32);
    }
    if scan.label.is_some() {
        add("label", Numeric::U32);
    }
    for (name, _) in extra {
        add(name, Numeric::F32);
    }
    let point_step = offset;
    let n = scan.len();
    let mut data = Vec::with_capacity(n * point_step as usize);
    for i in 0..n {
        for c in scan.xyz[i] {
            data.extend_from_slice(&c.to_le_bytes());
        }
        if let Some(v) = &scan.intensity {
            data.extend_from_slice(&v[i].to_le_bytes());
        }
        if let Some(v) = &scan.ring {
            data.extend_from_slice(&v[i].to_le_bytes());
        }
        if let Some(v) = &scan.time_s {
            data.extend_from_slice(&v[i].to_le_bytes());
        }
        if let Some(v) = &scan.label {
            data.extend_from_slice(&v[i].to_le_bytes());
        }
        for (_, v) in extra {
            data.extend_from_slice(&v.get(i).copied().unwrap_or(f32::NAN).to_le_bytes());
        }
    }
    let (height, width) = if scan.height * scan.width == n {
        (scan.height, scan.width)
    } else {
        (1, n)
    };
    let layout = CloudLayout {
        fields,
        point_step,
        row_step: point_step * width as u32,
        height: height as u32,
        width: width as u32,
        big_endian: false,
    };
    (layout, data)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ros_and_foxglove_codes_differ_for_integers() {
        assert_eq!(Numeric::from_ros(2), Some(Numeric::U8));
        assert_eq!(Numeric::from_foxglove(2), Some(Numeric::I8));
        assert_eq!(Numeric::from_ros(7), Numeric::from_foxglove(7));
        assert_eq!(Numeric::from_ros(0), None);
        assert_eq!(Numeric::from_foxglove(9), None);
        for n in Numeric::ROS {
            assert_eq!(Numeric::from_ros(n.ros_code()), Some(n));
            assert_eq!(Numeric::from_foxglove(n.foxglove_code()), Some(n));
        }
    }

    #[test]
    fn encode_decode_round_trip_keeps_every_field() {
        let scan = Scan {
            xyz: vec![[1.0, 2.0, 3.0], [-4.0, 5.5, f32::NAN]],
            intensity: Some(vec![0.5, 7.0]),
            ring: Some(vec![3, 63]),
            time_s: Some(vec![0.0, 0.05]),
            label: Some(vec![40, 10 | (7 << 16)]),
            height: 1,
            width: 2,
        };
        let (layout, data) = encode(&scan, &[]);
        let (back, _) = layout.decode(&data).unwrap();
        assert_eq!(back.xyz[0], scan.xyz[0]);
        assert!(back.xyz[1][2].is_nan());
        assert_eq!(
            (back.intensity, back.ring, back.time_s, back.label),
            (scan.intensity, scan.ring, scan.time_s, scan.label)
        );
    }

    #[test]
    fn big_endian_float64_and_integer_time_decode() {
        // x, y, z float64 big-endian; t uint32 nanoseconds; reflectivity uint16.
        let layout = CloudLayout {
            fields: vec![
                Field {
                    name: "x".into(),
                    offset: 0,
                    numeric: Numeric::F64,
                    count: 1,
                },
                Field {
                    name: "y".into(),
                    offset: 8,
                    numeric: Numeric::F64,
                    count: 1,
                },
                Field {
                    name: "z".into(),
                    offset: 16,
                    numeric: Numeric::F64,
                    count: 1,
                },
                Field {
                    name: "t".into(),
                    offset: 24,
                    numeric: Numeric::U32,
                    count: 1,
                },
                Field {
                    name: "reflectivity".into(),
                    offset: 28,
                    numeric: Numeric::U16,
                    count: 1,
                },
            ],
            point_step: 32,
            row_step: 32,
            height: 1,
            width: 1,
            big_endian: true,
        };
        let mut data = Vec::new();
        for v in [1.5f64, -2.0, 0.25] {
            data.extend_from_slice(&v.to_be_bytes());
        }
        data.extend_from_slice(&50_000_000u32.to_be_bytes());
        data.extend_from_slice(&300u16.to_be_bytes());
        data.extend_from_slice(&[0, 0]);
        let (scan, _) = layout.decode(&data).unwrap();
        assert_eq!(scan.xyz, vec![[1.5, -2.0, 0.25]]);
        assert_eq!(scan.time_s, Some(vec![0.05]));
        assert_eq!(scan.intensity, Some(vec![300.0]));
    }

    #[test]
    fn malformed_layouts_are_errors_not_panics() {
        let (mut layout, data) = encode(&Scan::from_xyz(vec![[1.0, 2.0, 3.0]; 4]), &[]);
        assert!(matches!(
            layout.decode(&data[..20]),
            Err(CloudError::DataTooShort { .. })
        ));
        layout.fields[0].offset = 10;
        assert!(matches!(
            layout.decode(&data),
            Err(CloudError::FieldOutsidePoint { .. })
        ));
        // An offset near 2^32 must not wrap around to a small end byte.
        layout.fields[0].offset = u32::MAX - 1;
        let err = layout.decode(&data).unwrap_err().to_string();
        assert!(err.contains("ends at byte 4294967298"), "{err}");
        layout.fields.remove(0);
        let err = layout.decode(&data).unwrap_err().to_string();
        assert!(
            err.contains("no \"x\" field") && err.contains("found: y, z"),
            "{err}"
        );
    }
}
