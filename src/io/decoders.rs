//! Point-cloud message decoders, looked up by (message encoding, schema name):
//! ROS 2 `sensor_msgs/msg/PointCloud2` (cdr), ROS 1 `sensor_msgs/PointCloud2`
//! (ros1), and `foxglove.PointCloud` (protobuf or json). Every one ends in the
//! shared [`CloudLayout::decode`].

use foxglove::Decode;

use super::pointcloud::{CloudError, CloudLayout, Field, Numeric};
use super::wire::WireReader;
use crate::lidar::Scan;

/// The message families we read and write. Output channels use the input's family.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Family {
    Ros2,
    Ros1,
    Foxglove,
}

/// A point-cloud message format we can decode.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum CloudFormat {
    Ros2Cdr,
    Ros1,
    FoxgloveProtobuf,
    FoxgloveJson,
}

impl CloudFormat {
    /// The decoder for a channel, or `None` when it is not a point cloud we know.
    pub fn detect(message_encoding: &str, schema_name: &str) -> Option<Self> {
        let ros_cloud = matches!(
            schema_name,
            "sensor_msgs/msg/PointCloud2" | "sensor_msgs/PointCloud2"
        );
        match (message_encoding, schema_name) {
            ("cdr", _) if ros_cloud => Some(CloudFormat::Ros2Cdr),
            ("ros1", _) if ros_cloud => Some(CloudFormat::Ros1),
            ("protobuf", "foxglove.PointCloud") => Some(CloudFormat::FoxgloveProtobuf),
            ("json", "foxglove.PointCloud") => Some(CloudFormat::FoxgloveJson),
            _ => None,
        }
    }

    pub fn family(self) -> Family {
        match self {
            CloudFormat::Ros2Cdr => Family::Ros2,
            CloudFormat::Ros1 => Family::Ros1,
            CloudFormat::FoxgloveProtobuf | CloudFormat::FoxgloveJson => Family::Foxglove,
        }
    }
}

/// A decoded point-cloud message.
#[derive(Debug, Clone, PartialEq)]
pub struct DecodedCloud {
    pub scan: Scan,
    /// The header stamp (sensor time), nanoseconds.
    pub stamp_nanos: u64,
    pub frame_id: String,
    /// What was read differently from the message's word (see [`CloudLayout::decode`]):
    /// each a warning for whoever reports on the scan.
    pub notes: Vec<String>,
}

/// Decodes one message of `format`.
pub fn decode_cloud(format: CloudFormat, data: &[u8]) -> Result<DecodedCloud, CloudError> {
    match format {
        CloudFormat::Ros2Cdr => decode_ros(WireReader::cdr(data)?),
        CloudFormat::Ros1 => decode_ros(WireReader::ros1(data)),
        CloudFormat::FoxgloveProtobuf => {
            let msg = foxglove::messages::PointCloud::decode(data)
                .map_err(|e| CloudError::Other(format!("protobuf: {e}")))?;
            decode_foxglove(&msg)
        }
        CloudFormat::FoxgloveJson => {
            let mut value: serde_json::Value = serde_json::from_slice(data)
                .map_err(|e| CloudError::Other(format!("json: {e}")))?;
            numeric_type_names(&mut value);
            let msg: foxglove::messages::PointCloud = serde_json::from_value(value)
                .map_err(|e| CloudError::Other(format!("json: {e}")))?;
            decode_foxglove(&msg)
        }
    }
}

/// Foxglove's JSON schema gives `PackedElementField.type` as an integer code, its
/// protobuf JSON mapping as the enum name: integer codes become names so that both
/// parse (an unknown code stays a number and is reported as unknown by the parser).
fn numeric_type_names(msg: &mut serde_json::Value) {
    use foxglove::messages::packed_element_field::NumericType;
    let Some(fields) = msg.get_mut("fields").and_then(|f| f.as_array_mut()) else {
        return;
    };
    for field in fields {
        let Some(ty) = field.get_mut("type") else {
            continue;
        };
        if let Some(name) = ty
            .as_i64()
            .and_then(|code| i32::try_from(code).ok())
            .and_then(|code| NumericType::try_from(code).ok())
        {
            *ty = serde_json::Value::String(name.as_str_name().to_string());
        }
    }
}

fn decode_ros(mut r: WireReader<'_>) -> Result<DecodedCloud, CloudError> {
    let (stamp_nanos, frame_id) = r.header()?;
    let height = r.u32("height")?;
    let width = r.u32("width")?;
    let n_fields = r.u32("fields")?;
    let mut fields = Vec::new();
    for _ in 0..n_fields {
        let name = r.string("fields.name")?.to_string();
        let offset = r.u32("fields.offset")?;
        let code = r.u8("fields.datatype")?;
        let count = r.u32("fields.count")?;
        let numeric = Numeric::from_ros(code).ok_or_else(|| CloudError::UnknownDatatype {
            name: name.clone(),
            code: code as i32,
        })?;
        fields.push(Field {
            name,
            offset,
            numeric,
            count,
        });
    }
    let big_endian = r.u8("is_bigendian")? != 0;
    let point_step = r.u32("point_step")?;
    let row_step = r.u32("row_step")?;
    let data = r.bytes("data")?;
    let layout = CloudLayout {
        fields,
        point_step,
        row_step,
        height,
        width,
        big_endian,
    };
    let (scan, notes) = layout.decode(data)?;
    Ok(DecodedCloud {
        scan,
        stamp_nanos,
        frame_id: frame_id.to_string(),
        notes,
    })
}

fn decode_foxglove(msg: &foxglove::messages::PointCloud) -> Result<DecodedCloud, CloudError> {
    let mut fields = Vec::new();
    for f in &msg.fields {
        let numeric =
            Numeric::from_foxglove(f.r#type).ok_or_else(|| CloudError::UnknownDatatype {
                name: f.name.clone(),
                code: f.r#type,
            })?;
        fields.push(Field {
            name: f.name.clone(),
            offset: f.offset,
            numeric,
            count: 1,
        });
    }
    let stride = msg.point_stride;
    if stride == 0 {
        return Err(CloudError::Other("point_stride is 0".into()));
    }
    let width = (msg.data.len() / stride as usize) as u32;
    let layout = CloudLayout {
        fields,
        point_step: stride,
        row_step: stride * width,
        height: 1,
        width,
        big_endian: false,
    };
    let (scan, notes) = layout.decode(&msg.data)?;
    Ok(DecodedCloud {
        scan,
        stamp_nanos: msg.timestamp.map_or(0, |t| t.total_nanos()),
        frame_id: msg.frame_id.clone(),
        notes,
    })
}
