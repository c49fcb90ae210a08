//! Writes the hostile recordings that BENCHMARKS.md measures peak memory on, each made
//! from a valid recording the way a broken recorder or an attacker would damage it:
//!
//!     cargo run --release --example hostile_inputs -- DIR
//!
//! `valid.mcap` (40 scans of 5 184 points, ROS 2, zstd chunks of ~100 KB),
//! `one_big_chunk.mcap` (200 such scans in one 21 MB chunk, to calibrate the bound),
//! `huge_chunk_size.mcap` (one chunk declares 2^50 uncompressed bytes),
//! `huge_record_length.mcap` (a mid-file chunk record claims 2^62 bytes),
//! `huge_string_length.mcap` (a chunk's compression name claims 4 GB),
//! `rings_20000.mcap` and `rings_65536.mcap` (one scan whose uint16 ring field holds
//! that many distinct values).

use std::collections::BTreeMap;
use std::path::Path;

use rangegan_mcap::io::decoders::{DecodedCloud, Family};
use rangegan_mcap::io::encoders::{self, Kind};
use rangegan_mcap::lidar::{Scan, SensorProfile};

/// A 16-beam, 360-column cylinder wall, ring field included.
fn wall(range_m: f32) -> Scan {
    let grid = SensorProfile::builtin("vlp16")
        .expect("built-in profile")
        .with_columns(324)
        .angle_grid();
    let mut scan = Scan::from_xyz(
        (0..grid.len())
            .map(|k| grid.direction(k).map(|d| d * range_m))
            .collect(),
    );
    scan.ring = Some((0..grid.len()).map(|k| (15 - k / 324) as u16).collect());
    scan
}

/// A scan of `n` points on a sphere whose ring field holds `n` distinct values.
fn distinct_rings(n: usize) -> Scan {
    let mut scan = Scan::from_xyz(
        (0..n)
            .map(|i| {
                let (az, el) = (i as f32 * 0.0001, (i as f32 / n as f32 - 0.5) * 0.5);
                [
                    10.0 * el.cos() * az.cos(),
                    10.0 * el.cos() * az.sin(),
                    10.0 * el.sin(),
                ]
            })
            .collect(),
    );
    scan.ring = Some((0..n).map(|i| i as u16).collect());
    scan
}

fn write(path: &Path, scans: &[Scan], chunk_size: Option<u64>) -> Vec<u8> {
    let mut w = mcap::WriteOptions::new()
        .compression(Some(mcap::Compression::Zstd))
        .chunk_size(chunk_size)
        .create(std::io::Cursor::new(Vec::new()))
        .expect("writer");
    let s = encoders::schema(Family::Ros2, Kind::Cloud);
    let schema = w.add_schema(&s.name, &s.encoding, &s.data).expect("schema");
    let channel = w
        .add_channel(schema, "/points", "cdr", &BTreeMap::new())
        .expect("channel");
    for (i, scan) in scans.iter().enumerate() {
        let t = 1_000_000_000 + i as u64 * 100_000_000;
        let cloud = DecodedCloud {
            scan: scan.clone(),
            stamp_nanos: t,
            frame_id: "lidar".into(),
            notes: Vec::new(),
        };
        let header = mcap::records::MessageHeader {
            channel_id: channel,
            sequence: i as u32,
            log_time: t,
            publish_time: t,
        };
        let data = encoders::encode_scan(Family::Ros2, &cloud, &[]);
        w.write_to_known_channel(&header, &data).expect("message");
    }
    w.finish().expect("finish");
    let bytes = w.into_inner().into_inner();
    std::fs::write(path, &bytes).expect("write");
    bytes
}

/// File offsets of the top-level chunk records.
fn chunks(bytes: &[u8]) -> Vec<usize> {
    let (mut pos, mut found) = (8, Vec::new());
    while pos + 9 <= bytes.len() && bytes[pos] != 0x02 {
        if bytes[pos] == 0x06 {
            found.push(pos);
        }
        pos +=
            9 + u64::from_le_bytes(bytes[pos + 1..pos + 9].try_into().expect("8 bytes")) as usize;
    }
    found
}

/// `bytes` with `value` written at `at` (its low `width` bytes).
fn patched(bytes: &[u8], at: usize, value: u64, width: usize) -> Vec<u8> {
    let mut b = bytes.to_vec();
    b[at..at + width].copy_from_slice(&value.to_le_bytes()[..width]);
    b
}

fn main() {
    let dir = std::path::PathBuf::from(std::env::args().nth(1).expect("usage: hostile_inputs DIR"));
    std::fs::create_dir_all(&dir).expect("output folder");
    let scans: Vec<Scan> = (0..40).map(|i| wall(5.0 + i as f32 * 0.5)).collect();
    let valid = write(&dir.join("valid.mcap"), &scans, Some(16 * 1024));
    // The same drive, 5 times over, in one chunk: the largest record sets the bound.
    let long: Vec<Scan> = (0..200)
        .map(|i| wall(5.0 + (i % 40) as f32 * 0.5))
        .collect();
    write(&dir.join("one_big_chunk.mcap"), &long, None);
    let at = chunks(&valid);
    let middle = at[at.len() / 2];
    // Chunk body: start, end, uncompressed size (u64), CRC (u32), compression (u32 + name).
    let damaged = [
        (
            "huge_chunk_size.mcap",
            patched(&valid, at[1] + 9 + 16, 1 << 50, 8),
        ),
        (
            "huge_record_length.mcap",
            patched(&valid, middle + 1, 1 << 62, 8),
        ),
        (
            "huge_string_length.mcap",
            patched(&valid, middle + 9 + 28, 0xffff_ff00, 4),
        ),
    ];
    for (name, bytes) in damaged {
        std::fs::write(dir.join(name), bytes).expect("write");
    }
    write(
        &dir.join("rings_20000.mcap"),
        &[distinct_rings(20_000)],
        Some(16 * 1024),
    );
    write(
        &dir.join("rings_65536.mcap"),
        &[distinct_rings(65_536)],
        Some(16 * 1024),
    );
    println!("hostile recordings written to {}", dir.display());
}
