//! Both ends of a conversion as the evaluations and tests drive it: scans written as a plain
//! ROS 2 recording, and the float images `convert` writes read back from its output.

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::Context;

use super::decoders::{DecodedCloud, Family};
use super::encoders::{self, Kind};
use super::wire::{WireError, WireReader};
use crate::lidar::Scan;

/// Writes `scans` as one ROS 2 recording of `sensor_msgs/msg/PointCloud2` on `topic`, 100 ms
/// apart from 1 s.
pub fn write_scans(path: &Path, topic: &str, frame_id: &str, scans: &[Scan]) -> anyhow::Result<()> {
    let file =
        std::fs::File::create(path).with_context(|| format!("cannot create {}", path.display()))?;
    let mut w = mcap::WriteOptions::new().create(std::io::BufWriter::new(file))?;
    let s = encoders::schema(Family::Ros2, Kind::Cloud);
    let schema = w.add_schema(&s.name, &s.encoding, &s.data)?;
    let channel = w.add_channel(schema, topic, "cdr", &BTreeMap::new())?;
    for (k, scan) in scans.iter().enumerate() {
        let t = 1_000_000_000 + k as u64 * 100_000_000;
        let cloud = DecodedCloud {
            scan: scan.clone(),
            stamp_nanos: t,
            frame_id: frame_id.into(),
            notes: Vec::new(),
        };
        let header = mcap::records::MessageHeader {
            channel_id: channel,
            sequence: k as u32,
            log_time: t,
            publish_time: t,
        };
        w.write_to_known_channel(&header, &encoders::encode_scan(Family::Ros2, &cloud, &[]))?;
    }
    w.finish()?;
    Ok(())
}

/// A `32FC1` image: height, width and row-major values.
#[derive(Debug, Clone, PartialEq)]
pub struct FloatImage {
    pub height: usize,
    pub width: usize,
    pub values: Vec<f32>,
}

/// Decodes a ROS 1 (`ros1`) or ROS 2 (`cdr`) `sensor_msgs/Image` of little-endian floats.
pub fn decode_float_image(message_encoding: &str, data: &[u8]) -> Result<FloatImage, WireError> {
    let mut r = match message_encoding {
        "ros1" => WireReader::ros1(data),
        _ => WireReader::cdr(data)?,
    };
    r.header()?;
    let height = r.u32("height")? as usize;
    let width = r.u32("width")? as usize;
    r.string("encoding")?;
    r.u8("is_bigendian")?;
    r.u32("step")?;
    let values = (r.bytes("data")?.chunks_exact(4))
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    Ok(FloatImage {
        height,
        width,
        values,
    })
}

/// The float images on `topic` of the recording `bytes`, in log-time order.
pub fn float_images(bytes: &[u8], topic: &str) -> anyhow::Result<Vec<FloatImage>> {
    let mut out = Vec::new();
    for m in mcap::MessageStream::new(bytes)? {
        let m = m?;
        if m.channel.topic == topic {
            let image = decode_float_image(&m.channel.message_encoding, &m.data)
                .with_context(|| format!("{topic} at {} ns", m.log_time))?;
            out.push((m.log_time, image));
        }
    }
    out.sort_by_key(|(t, _)| *t);
    Ok(out.into_iter().map(|(_, i)| i).collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::encoders::encode_f32_image;

    #[test]
    fn float_images_round_trip_in_both_ros_families() {
        for family in [Family::Ros1, Family::Ros2] {
            let data =
                encode_f32_image(family, 5, "lidar", (3, 2), &[1.0, 2.0, 3.0, 4.0, 5.0, 6.0]);
            let encoding = encoders::message_encoding(family);
            let image = decode_float_image(encoding, &data).unwrap();
            assert_eq!((image.height, image.width), (2, 3));
            assert_eq!(image.values, [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]);
        }
    }
}
