//! The single encoding layer for every output channel: a [`Payload`] (image,
//! point cloud, transforms) becomes message bytes in the input's [`Family`], with
//! the matching schema ([`schema`]) and message encoding.

use foxglove::Encode;

use super::decoders::{DecodedCloud, Family};
use super::pointcloud::CloudLayout;
use super::wire::WireWriter;
use crate::lidar::Scan;

/// A schema record to register: name, schema encoding and text/bytes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SchemaDef {
    pub name: String,
    pub encoding: String,
    pub data: Vec<u8>,
}

/// Pixel formats of output images (ROS `sensor_msgs/Image` encodings).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PixelFormat {
    /// One little-endian float32 per pixel (`32FC1`).
    F32,
    /// One byte per pixel (`mono8`).
    Mono8,
}

impl PixelFormat {
    pub fn ros_name(self) -> &'static str {
        match self {
            PixelFormat::F32 => "32FC1",
            PixelFormat::Mono8 => "mono8",
        }
    }

    fn bytes_per_pixel(self) -> u32 {
        match self {
            PixelFormat::F32 => 4,
            PixelFormat::Mono8 => 1,
        }
    }
}

/// A rigid transform between two frames (meters, unit quaternion x, y, z, w).
#[derive(Debug, Clone, PartialEq)]
pub struct Transform {
    pub parent_frame_id: String,
    pub child_frame_id: String,
    pub translation: [f64; 3],
    pub rotation: [f64; 4],
}

/// What an output message carries.
#[derive(Debug, Clone)]
pub enum Payload<'a> {
    Image {
        width: u32,
        height: u32,
        format: PixelFormat,
        data: &'a [u8],
    },
    Cloud {
        layout: &'a CloudLayout,
        data: &'a [u8],
    },
    Transforms(&'a [Transform]),
}

/// The kind of a payload, which fixes the schema of its channel.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Kind {
    Image,
    Cloud,
    Transforms,
}

impl Payload<'_> {
    pub fn kind(&self) -> Kind {
        match self {
            Payload::Image { .. } => Kind::Image,
            Payload::Cloud { .. } => Kind::Cloud,
            Payload::Transforms(_) => Kind::Transforms,
        }
    }
}

/// The message encoding of channels written in `family`.
pub fn message_encoding(family: Family) -> &'static str {
    match family {
        Family::Ros2 => "cdr",
        Family::Ros1 => "ros1",
        Family::Foxglove => "protobuf",
    }
}

fn foxglove_schema<T: Encode>() -> SchemaDef {
    let s = T::get_schema().unwrap_or_else(|| foxglove::Schema::new("", "", Vec::new()));
    SchemaDef {
        name: s.name,
        encoding: s.encoding,
        data: s.data.into_owned(),
    }
}

/// A kind's ROS package and type, with its ROS 2 and ROS 1 definitions.
fn ros_type(kind: Kind) -> (&'static str, &'static str, &'static str, &'static str) {
    match kind {
        Kind::Image => (
            "sensor_msgs",
            "Image",
            include_str!("../../schemas/ros2/sensor_msgs__Image.msg"),
            include_str!("../../schemas/ros1/sensor_msgs__Image.msg"),
        ),
        Kind::Cloud => (
            "sensor_msgs",
            "PointCloud2",
            include_str!("../../schemas/ros2/sensor_msgs__PointCloud2.msg"),
            include_str!("../../schemas/ros1/sensor_msgs__PointCloud2.msg"),
        ),
        Kind::Transforms => (
            "tf2_msgs",
            "TFMessage",
            include_str!("../../schemas/ros2/tf2_msgs__TFMessage.msg"),
            include_str!("../../schemas/ros1/tf2_msgs__TFMessage.msg"),
        ),
    }
}

/// The schema of a `kind` channel in `family`.
pub fn schema(family: Family, kind: Kind) -> SchemaDef {
    let ros = |ros2: bool| {
        let (package, name, text2, text1) = ros_type(kind);
        let (name, encoding, text) = if ros2 {
            (format!("{package}/msg/{name}"), "ros2msg", text2)
        } else {
            (format!("{package}/{name}"), "ros1msg", text1)
        };
        SchemaDef {
            name,
            encoding: encoding.into(),
            data: text.as_bytes().to_vec(),
        }
    };
    match (family, kind) {
        (Family::Ros2, _) => ros(true),
        (Family::Ros1, _) => ros(false),
        (Family::Foxglove, Kind::Image) => foxglove_schema::<foxglove::messages::RawImage>(),
        (Family::Foxglove, Kind::Cloud) => foxglove_schema::<foxglove::messages::PointCloud>(),
        (Family::Foxglove, Kind::Transforms) => {
            foxglove_schema::<foxglove::messages::FrameTransforms>()
        }
    }
}

fn timestamp(nanos: u64) -> foxglove::messages::Timestamp {
    foxglove::messages::Timestamp::new(
        (nanos / 1_000_000_000) as u32,
        (nanos % 1_000_000_000) as u32,
    )
}

fn protobuf<T: Encode>(msg: &T) -> Vec<u8> {
    let mut buf = Vec::with_capacity(msg.encoded_len().unwrap_or(64));
    // Encoding into a growable Vec cannot run out of space.
    let _ = msg.encode(&mut buf);
    buf
}

/// Encodes `payload` as a message of `family`, stamped `stamp_nanos` in `frame_id`.
pub fn encode(family: Family, stamp_nanos: u64, frame_id: &str, payload: &Payload<'_>) -> Vec<u8> {
    match family {
        Family::Ros2 | Family::Ros1 => encode_ros(family, stamp_nanos, frame_id, payload),
        Family::Foxglove => encode_foxglove(stamp_nanos, frame_id, payload),
    }
}

fn encode_ros(family: Family, stamp_nanos: u64, frame_id: &str, payload: &Payload<'_>) -> Vec<u8> {
    let size = match payload {
        Payload::Image { data, .. } | Payload::Cloud { data, .. } => data.len(),
        Payload::Transforms(t) => t.len() * 128,
    };
    let mut w = if family == Family::Ros1 {
        WireWriter::ros1(size + 256)
    } else {
        WireWriter::cdr(size + 256)
    };
    match payload {
        Payload::Image {
            width,
            height,
            format,
            data,
        } => {
            w.header(stamp_nanos, frame_id)
                .u32(*height)
                .u32(*width)
                .string(format.ros_name())
                .u8(0)
                .u32(width * format.bytes_per_pixel())
                .bytes(data);
        }
        Payload::Cloud { layout, data } => {
            w.header(stamp_nanos, frame_id)
                .u32(layout.height)
                .u32(layout.width)
                .u32(layout.fields.len() as u32);
            for f in &layout.fields {
                w.string(&f.name)
                    .u32(f.offset)
                    .u8(f.numeric.ros_code())
                    .u32(f.count);
            }
            w.u8(layout.big_endian as u8)
                .u32(layout.point_step)
                .u32(layout.row_step)
                .bytes(data)
                .u8(0);
        }
        Payload::Transforms(transforms) => {
            w.u32(transforms.len() as u32);
            for t in transforms.iter() {
                w.header(stamp_nanos, &t.parent_frame_id)
                    .string(&t.child_frame_id);
                for v in t.translation.iter().chain(t.rotation.iter()) {
                    w.f64(*v);
                }
            }
        }
    }
    w.finish()
}

fn encode_foxglove(stamp_nanos: u64, frame_id: &str, payload: &Payload<'_>) -> Vec<u8> {
    use foxglove::messages as fm;
    let ts = Some(timestamp(stamp_nanos));
    match payload {
        Payload::Image {
            width,
            height,
            format,
            data,
        } => protobuf(&fm::RawImage {
            timestamp: ts,
            frame_id: frame_id.into(),
            width: *width,
            height: *height,
            encoding: format.ros_name().into(),
            step: width * format.bytes_per_pixel(),
            data: foxglove::bytes::Bytes::copy_from_slice(data),
        }),
        Payload::Cloud { layout, data } => protobuf(&fm::PointCloud {
            timestamp: ts,
            frame_id: frame_id.into(),
            pose: None,
            point_stride: layout.point_step,
            fields: layout
                .fields
                .iter()
                .map(|f| fm::PackedElementField {
                    name: f.name.clone(),
                    offset: f.offset,
                    r#type: f.numeric.foxglove_code(),
                })
                .collect(),
            data: foxglove::bytes::Bytes::copy_from_slice(data),
        }),
        Payload::Transforms(transforms) => protobuf(&fm::FrameTransforms {
            transforms: transforms
                .iter()
                .map(|t| fm::FrameTransform {
                    timestamp: ts,
                    parent_frame_id: t.parent_frame_id.clone(),
                    child_frame_id: t.child_frame_id.clone(),
                    translation: Some(fm::Vector3 {
                        x: t.translation[0],
                        y: t.translation[1],
                        z: t.translation[2],
                    }),
                    rotation: Some(fm::Quaternion {
                        x: t.rotation[0],
                        y: t.rotation[1],
                        z: t.rotation[2],
                        w: t.rotation[3],
                    }),
                })
                .collect(),
        }),
    }
}

/// Encodes a decoded cloud's scan again, with its stamp and frame (see [`encode_cloud`]).
pub fn encode_scan(family: Family, cloud: &DecodedCloud, extra: &[(&str, &[f32])]) -> Vec<u8> {
    encode_cloud(
        family,
        cloud.stamp_nanos,
        &cloud.frame_id,
        &cloud.scan,
        extra,
    )
}

/// Encodes a scan as a point-cloud message of `family` (x, y, z and the scan's
/// optional fields, then `extra` float channels).
pub fn encode_cloud(
    family: Family,
    stamp_nanos: u64,
    frame_id: &str,
    scan: &Scan,
    extra: &[(&str, &[f32])],
) -> Vec<u8> {
    let (layout, data) = super::pointcloud::encode(scan, extra);
    encode(
        family,
        stamp_nanos,
        frame_id,
        &Payload::Cloud {
            layout: &layout,
            data: &data,
        },
    )
}

/// A float image (`32FC1`) of `width x height` row-major values.
pub fn encode_f32_image(
    family: Family,
    stamp_nanos: u64,
    frame_id: &str,
    (width, height): (usize, usize),
    values: &[f32],
) -> Vec<u8> {
    let data: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
    encode_image(
        family,
        stamp_nanos,
        frame_id,
        (width, height),
        PixelFormat::F32,
        &data,
    )
}

/// A ray-drop mask (`mono8`, 255 = the return was kept, 0 = dropped).
pub fn encode_mask(
    family: Family,
    stamp_nanos: u64,
    frame_id: &str,
    (width, height): (usize, usize),
    kept: &[bool],
) -> Vec<u8> {
    let data: Vec<u8> = kept.iter().map(|&k| if k { 255 } else { 0 }).collect();
    encode_image(
        family,
        stamp_nanos,
        frame_id,
        (width, height),
        PixelFormat::Mono8,
        &data,
    )
}

/// An image message of `family` from its pixel bytes (row-major, `format`).
fn encode_image(
    family: Family,
    stamp_nanos: u64,
    frame_id: &str,
    (width, height): (usize, usize),
    format: PixelFormat,
    data: &[u8],
) -> Vec<u8> {
    let image = Payload::Image {
        width: width as u32,
        height: height as u32,
        format,
        data,
    };
    encode(family, stamp_nanos, frame_id, &image)
}

/// Encodes bare points (x, y, z, then `extra` float channels, one value per point) as an
/// unorganized point-cloud message of `family`, e.g. a completed scan with `range` and
/// `raydrop_prob`.
pub fn encode_points(
    family: Family,
    stamp_nanos: u64,
    frame_id: &str,
    xyz: Vec<[f32; 3]>,
    extra: &[(&str, &[f32])],
) -> Vec<u8> {
    encode_cloud(family, stamp_nanos, frame_id, &Scan::from_xyz(xyz), extra)
}

#[cfg(test)]
mod tests {
    use super::super::decoders::{CloudFormat, decode_cloud};
    use super::*;
    use crate::lidar::Scan;

    fn cloud() -> DecodedCloud {
        let mut scan = Scan::from_xyz(vec![[1.0, 2.0, 3.0], [4.0, -5.0, 6.5], [0.5, 0.25, -1.0]]);
        scan.intensity = Some(vec![10.0, 20.0, 30.0]);
        scan.ring = Some(vec![0, 1, 2]);
        DecodedCloud {
            scan,
            stamp_nanos: 1_700_000_000_123_456_789,
            frame_id: "lidar".into(),
            notes: Vec::new(),
        }
    }

    #[test]
    fn every_family_round_trips_a_cloud() {
        let c = cloud();
        for (family, format) in [
            (Family::Ros2, CloudFormat::Ros2Cdr),
            (Family::Ros1, CloudFormat::Ros1),
            (Family::Foxglove, CloudFormat::FoxgloveProtobuf),
        ] {
            let bytes = encode_scan(family, &c, &[]);
            assert_eq!(decode_cloud(format, &bytes).unwrap(), c, "{family:?}");
            let s = schema(family, Kind::Cloud);
            assert_eq!(
                CloudFormat::detect(message_encoding(family), &s.name),
                Some(format)
            );
        }
    }

    #[test]
    fn bare_points_round_trip_with_extra_fields() {
        let xyz = vec![[1.0, 2.0, 3.0], [-4.0, 0.5, 0.0]];
        let range = [3.74f32, 4.03];
        let drop = [0.1f32, 0.9];
        for (family, format) in [
            (Family::Ros2, CloudFormat::Ros2Cdr),
            (Family::Ros1, CloudFormat::Ros1),
            (Family::Foxglove, CloudFormat::FoxgloveProtobuf),
        ] {
            let bytes = encode_points(
                family,
                7,
                "lidar",
                xyz.clone(),
                &[("range", &range), ("raydrop_prob", &drop)],
            );
            let back = decode_cloud(format, &bytes).unwrap();
            assert_eq!(back.scan.xyz, xyz, "{family:?}");
            assert_eq!((back.stamp_nanos, back.frame_id.as_str()), (7, "lidar"));
        }
    }

    #[test]
    fn foxglove_json_clouds_decode_with_base64_data() {
        let c = cloud();
        let (layout, data) = super::super::pointcloud::encode(&c.scan, &[]);
        let msg = foxglove::messages::PointCloud {
            timestamp: Some(timestamp(c.stamp_nanos)),
            frame_id: c.frame_id.clone(),
            pose: None,
            point_stride: layout.point_step,
            fields: layout
                .fields
                .iter()
                .map(|f| foxglove::messages::PackedElementField {
                    name: f.name.clone(),
                    offset: f.offset,
                    r#type: f.numeric.foxglove_code(),
                })
                .collect(),
            data: data.into(),
        };
        let json = serde_json::to_vec(&msg).unwrap();
        assert!(
            String::from_utf8_lossy(&json).contains("\"data\":\""),
            "bytes as base64 text"
        );
        assert_eq!(decode_cloud(CloudFormat::FoxgloveJson, &json).unwrap(), c);
    }

    /// Foxglove's JSON schema writes `PackedElementField.type` as an integer code: both
    /// that and the enum name decode to the same cloud.
    #[test]
    fn foxglove_json_with_integer_type_codes_decodes() {
        let c = cloud();
        let (layout, data) = super::super::pointcloud::encode(&c.scan, &[]);
        let fields: Vec<serde_json::Value> = layout
            .fields
            .iter()
            .map(|f| serde_json::json!({"name": f.name, "offset": f.offset, "type": f.numeric.foxglove_code()}))
            .collect();
        use base64::Engine;
        let json = serde_json::json!({
            "timestamp": {"sec": c.stamp_nanos / 1_000_000_000, "nsec": c.stamp_nanos % 1_000_000_000},
            "frame_id": c.frame_id,
            "point_stride": layout.point_step,
            "fields": fields,
            "data": base64::engine::general_purpose::STANDARD.encode(&data),
        });
        let bytes = serde_json::to_vec(&json).unwrap();
        assert_eq!(decode_cloud(CloudFormat::FoxgloveJson, &bytes).unwrap(), c);
        // An integer that is no NumericType is reported as such, not as malformed JSON.
        let mut bad = json.clone();
        bad["fields"][0]["type"] = serde_json::json!(99);
        let err = decode_cloud(
            CloudFormat::FoxgloveJson,
            &serde_json::to_vec(&bad).unwrap(),
        )
        .unwrap_err()
        .to_string();
        assert!(err.contains("json"), "{err}");
    }

    #[test]
    fn ros2_image_has_the_sensor_msgs_layout() {
        let data: Vec<u8> = [1.5f32, 2.5].iter().flat_map(|v| v.to_le_bytes()).collect();
        let bytes = encode(
            Family::Ros2,
            5_000_000_001,
            "lidar",
            &Payload::Image {
                width: 2,
                height: 1,
                format: PixelFormat::F32,
                data: &data,
            },
        );
        let mut r = super::super::wire::WireReader::cdr(&bytes).unwrap();
        assert_eq!(r.header().unwrap(), (5_000_000_001, "lidar"));
        assert_eq!((r.u32("h").unwrap(), r.u32("w").unwrap()), (1, 2));
        assert_eq!(r.string("enc").unwrap(), "32FC1");
        assert_eq!(r.u8("be").unwrap(), 0);
        assert_eq!(r.u32("step").unwrap(), 8);
        assert_eq!(r.bytes("data").unwrap(), &data[..]);
    }
}
