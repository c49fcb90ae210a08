//! Writes a large synthetic recording for benchmarks: camera-sized binary
//! messages, small JSON messages and (optionally) ROS 2 point clouds, zstd chunks.
//!
//! `cargo run --release --example make_recording -- OUT.mcap SIZE_MB [--clouds]`

use std::collections::BTreeMap;

use rangegan_mcap::io::decoders::{DecodedCloud, Family};
use rangegan_mcap::io::encoders::{self, Kind};
use rangegan_mcap::lidar::{Scan, SensorProfile};

/// Deterministic bytes that compress about as little as already-compressed
/// camera data: pseudo-random words, every fourth one zero.
fn payload(len: usize, seed: u64) -> Vec<u8> {
    let mut x = seed
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    let mut out = Vec::with_capacity(len + 8);
    for w in 0..len.div_ceil(8) {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        let word = if w % 4 == 3 { 0 } else { x };
        out.extend_from_slice(&word.to_le_bytes());
    }
    out.truncate(len);
    out
}

fn cloud(i: u64) -> Scan {
    let grid = SensorProfile::kitti_hdl64e().angle_grid();
    let mut scan = Scan {
        intensity: Some(Vec::new()),
        ..Default::default()
    };
    for k in 0..grid.len() {
        let r = 5.0 + ((k as u64 * 7919 + i * 13) % 600) as f32 / 10.0;
        let [x, y, z] = grid.direction(k);
        scan.xyz.push([x * r, y * r, z * r]);
        if let Some(v) = scan.intensity.as_mut() {
            v.push((k % 100) as f32);
        }
    }
    scan.height = 1;
    scan.width = scan.xyz.len();
    scan
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let out = &args[1];
    let target_bytes: u64 = args[2].parse::<u64>()? * 1_000_000;
    let clouds = args.iter().any(|a| a == "--clouds");
    let file = std::io::BufWriter::with_capacity(1 << 20, std::fs::File::create(out)?);
    let mut w = mcap::WriteOptions::new()
        .compression(Some(mcap::Compression::Zstd))
        .create(file)?;
    let image_schema = w.add_schema("raw_bytes", "", b"")?;
    let camera = w.add_channel(
        image_schema,
        "/camera/raw",
        "application/octet-stream",
        &BTreeMap::new(),
    )?;
    let status = w.add_channel(0, "/status", "json", &BTreeMap::new())?;
    let s = encoders::schema(Family::Ros2, Kind::Cloud);
    let cloud_schema = w.add_schema(&s.name, &s.encoding, &s.data)?;
    let lidar = w.add_channel(cloud_schema, "/velodyne_points", "cdr", &BTreeMap::new())?;
    let mut written = 0u64;
    let mut i = 0u64;
    while written < target_bytes {
        let t = 1_600_000_000_000_000_000 + i * 100_000_000;
        let header = |channel_id| mcap::records::MessageHeader {
            channel_id,
            sequence: i as u32,
            log_time: t,
            publish_time: t,
        };
        let img = payload(1_000_000, i);
        w.write_to_known_channel(&header(camera), &img)?;
        written += img.len() as u64;
        let json = format!("{{\"seq\":{i},\"ok\":true}}");
        w.write_to_known_channel(&header(status), json.as_bytes())?;
        if clouds {
            let c = DecodedCloud {
                scan: cloud(i),
                stamp_nanos: t,
                frame_id: "velodyne".into(),
                notes: Vec::new(),
            };
            let data = encoders::encode_scan(Family::Ros2, &c, &[]);
            written += data.len() as u64;
            w.write_to_known_channel(&header(lidar), &data)?;
        }
        i += 1;
    }
    w.finish()?;
    eprintln!(
        "{out}: {i} frames, {:.0} MB of message data",
        written as f64 / 1e6
    );
    Ok(())
}
