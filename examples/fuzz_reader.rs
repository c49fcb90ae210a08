//! A bounded, reproducible fuzzer for the MCAP reader and the point-cloud decoders:
//! small valid recordings (ROS 2, ROS 1, Foxglove protobuf and JSON clouds; zstd, lz4
//! and uncompressed chunks, and no chunks) are mutated with bit flips, byte
//! overwrites, truncations, length-field overwrites (with the summary's chunk index intact),
//! spliced ranges, a channel id redefined with another topic, and damaged record lengths
//! inside uncompressed chunks, then read in-process. A panic fails the run and leaves the input in `tests/fuzz_regressions/`,
//! which the test suite replays. The address space is capped so that an allocation
//! sized by a damaged length aborts the run instead of passing unnoticed.
//!
//!     cargo run --release --example fuzz_reader -- --seconds 60 --seed 1

#[path = "../tests/common/fuzz.rs"]
mod fuzz;

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use rangegan_mcap::io::decoders::{DecodedCloud, Family};
use rangegan_mcap::io::encoders;
use rangegan_mcap::lidar::Scan;

/// SplitMix64: a fixed seed gives the same inputs on every machine.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
}

/// A small scan with a ring field (so every projection path is reachable).
fn scan(points: usize, seed: usize) -> Scan {
    let mut scan = Scan::from_xyz(
        (0..points)
            .map(|i| {
                let az = i as f32 * 0.37 + seed as f32;
                let el = ((i % 8) as f32 - 4.0) * 0.03;
                let r = 4.0 + (i % 13) as f32;
                [
                    r * el.cos() * az.cos(),
                    r * el.cos() * az.sin(),
                    r * el.sin(),
                ]
            })
            .collect(),
    );
    scan.intensity = Some((0..points).map(|i| (i % 100) as f32).collect());
    scan.ring = Some((0..points).map(|i| (i % 8) as u16).collect());
    scan
}

/// ROS 2 clouds of 8 x 12 points with hand-made layouts: an INT8 ring field holding
/// -4..3, a FLOAT32 ring with a NaN, coordinates scaled to ~1e30, and the same cloud
/// organized (8 x 12) and not (1 x 96).
fn hostile_layouts(seed: usize) -> Vec<Vec<u8>> {
    use rangegan_mcap::io::encoders::Payload;
    use rangegan_mcap::io::pointcloud::{CloudLayout, Field, Numeric};
    let field = |name: &str, offset: u32, numeric: Numeric| Field {
        name: name.into(),
        offset,
        numeric,
        count: 1,
    };
    let message = |ring: Option<Numeric>, scale: f32, organized: bool| {
        let mut fields = vec![
            field("x", 0, Numeric::F32),
            field("y", 4, Numeric::F32),
            field("z", 8, Numeric::F32),
        ];
        fields.extend(ring.map(|n| field("ring", 12, n)));
        let mut data = Vec::new();
        for b in 0..8usize {
            for c in 0..12usize {
                let (el, az) = ((b as f32 - 4.0) * 0.05, c as f32 * 0.52 + seed as f32);
                let r = 6.0 * if c == 3 { scale } else { 1.0 };
                for v in [
                    r * el.cos() * az.cos(),
                    r * el.cos() * az.sin(),
                    r * el.sin(),
                ] {
                    data.extend_from_slice(&v.to_le_bytes());
                }
                let ring_bytes = match ring {
                    Some(Numeric::I8) => vec![(b as i8 - 4) as u8, 0, 0, 0],
                    Some(_) => (if b == 2 { f32::NAN } else { b as f32 })
                        .to_le_bytes()
                        .to_vec(),
                    None => vec![0; 4],
                };
                data.extend_from_slice(&ring_bytes);
            }
        }
        let (height, width) = if organized { (8, 12) } else { (1, 96) };
        let layout = CloudLayout {
            fields,
            point_step: 16,
            row_step: 16 * width,
            height,
            width,
            big_endian: false,
        };
        let payload = Payload::Cloud {
            layout: &layout,
            data: &data,
        };
        encoders::encode(Family::Ros2, 1, "lidar", &payload)
    };
    vec![
        message(Some(Numeric::I8), 1.0, false),
        message(Some(Numeric::F32), 1.0, false),
        message(None, 1e29, false),
        message(None, 1.0, true),
        message(None, 1.0, false),
    ]
}

/// Valid recordings the mutations start from.
fn seeds() -> Vec<Vec<u8>> {
    let mut out = Vec::new();
    let compressions = [
        Some(mcap::Compression::Zstd),
        Some(mcap::Compression::Lz4),
        None,
    ];
    for (k, compression) in compressions.into_iter().enumerate() {
        for chunked in [true, false] {
            let mut w = mcap::WriteOptions::new()
                .compression(compression)
                .chunk_size(Some(2048))
                .use_chunks(chunked)
                .create(std::io::Cursor::new(Vec::new()))
                .expect("writer");
            for (c, family) in [Family::Ros2, Family::Ros1, Family::Foxglove]
                .iter()
                .enumerate()
            {
                let s = encoders::schema(*family, encoders::Kind::Cloud);
                let schema = w.add_schema(&s.name, &s.encoding, &s.data).expect("schema");
                let topic = format!("/lidar{c}");
                let channel = w
                    .add_channel(
                        schema,
                        &topic,
                        encoders::message_encoding(*family),
                        &BTreeMap::new(),
                    )
                    .expect("channel");
                for i in 0..3u64 {
                    let cloud = DecodedCloud {
                        scan: scan(60, k + c + i as usize),
                        stamp_nanos: i,
                        frame_id: "lidar".into(),
                        notes: Vec::new(),
                    };
                    let header = mcap::records::MessageHeader {
                        channel_id: channel,
                        sequence: i as u32,
                        log_time: i * 100,
                        publish_time: i * 100,
                    };
                    let data = encoders::encode_scan(*family, &cloud, &[]);
                    w.write_to_known_channel(&header, &data).expect("message");
                }
            }
            // A Foxglove JSON cloud with integer type codes.
            let schema = w
                .add_schema("foxglove.PointCloud", "jsonschema", b"{}")
                .expect("schema");
            let channel = w
                .add_channel(schema, "/json", "json", &BTreeMap::new())
                .expect("channel");
            let json = br#"{"timestamp":{"sec":1,"nsec":2},"frame_id":"l","point_stride":12,
                "fields":[{"name":"x","offset":0,"type":7},{"name":"y","offset":4,"type":7},
                {"name":"z","offset":8,"type":7}],"data":"AACAPwAAAEAAAEBAAACAPwAAAEAAAEBA"}"#;
            let header = mcap::records::MessageHeader {
                channel_id: channel,
                sequence: 0,
                log_time: 1,
                publish_time: 1,
            };
            w.write_to_known_channel(&header, json).expect("message");
            // Layouts that once lost returns without a word: signed and non-finite ring
            // values, coordinates near 1e30, a topic turning from organized to unorganized.
            let s = encoders::schema(Family::Ros2, encoders::Kind::Cloud);
            let schema = w.add_schema(&s.name, &s.encoding, &s.data).expect("schema");
            let channel = w
                .add_channel(schema, "/layouts", "cdr", &BTreeMap::new())
                .expect("channel");
            for (i, data) in hostile_layouts(k).iter().enumerate() {
                let header = mcap::records::MessageHeader {
                    channel_id: channel,
                    sequence: i as u32,
                    log_time: 10 + i as u64,
                    publish_time: 10 + i as u64,
                };
                w.write_to_known_channel(&header, data).expect("message");
            }
            w.attach(&mcap::Attachment {
                log_time: 1,
                create_time: 1,
                name: "calib.txt".into(),
                media_type: "text/plain".into(),
                data: std::borrow::Cow::Borrowed(b"P0: 1 0 0"),
            })
            .expect("attachment");
            w.write_metadata(&mcap::records::Metadata {
                name: "robot".into(),
                metadata: BTreeMap::from([("id".into(), "7".into())]),
            })
            .expect("metadata");
            w.finish().expect("finish");
            out.push(w.into_inner().into_inner());
        }
    }
    out
}

/// Offsets of the top-level records' length fields (opcode + 1).
fn length_fields(bytes: &[u8]) -> Vec<usize> {
    let mut pos = 8;
    let mut fields = Vec::new();
    while pos + 9 <= bytes.len() {
        fields.push(pos + 1);
        let len = u64::from_le_bytes(bytes[pos + 1..pos + 9].try_into().unwrap_or_default());
        match usize::try_from(len)
            .ok()
            .and_then(|l| (pos + 9).checked_add(l))
        {
            Some(next) if next > pos => pos = next,
            _ => break,
        }
    }
    fields
}

const INTERESTING: [u64; 9] = [
    0,
    1,
    0x7f,
    0x80,
    0xff,
    0xffff,
    1 << 31,
    u32::MAX as u64,
    1 << 62,
];

/// The top-level records: (opcode, offset, length of the body).
fn records(bytes: &[u8]) -> Vec<(u8, usize, usize)> {
    length_fields(bytes)
        .into_iter()
        .filter_map(|f| {
            let len = u64::from_le_bytes(bytes.get(f..f + 8)?.try_into().ok()?);
            let len = usize::try_from(len)
                .ok()
                .filter(|&l| f + 8 + l <= bytes.len())?;
            Some((bytes[f - 1], f - 1, len))
        })
        .collect()
}

/// A copy of a top-level channel record with one byte of its topic changed, inserted right
/// after it: the same id defined twice with different contents.
fn redefine_a_channel(b: &mut Vec<u8>, rng: &mut Rng) {
    let channels: Vec<_> = records(b).into_iter().filter(|r| r.0 == 0x04).collect();
    if channels.is_empty() {
        return;
    }
    let (_, at, len) = channels[rng.below(channels.len())];
    let mut copy = b[at..at + 9 + len].to_vec();
    // Body: id (2), schema id (2), topic length (4), topic.
    if let Some(byte) = copy.get_mut(9 + 8) {
        *byte ^= 0x20;
    }
    let end = at + 9 + len;
    b.splice(end..end, copy);
}

/// Inside an uncompressed chunk: its CRC cleared (so the records are walked) and the length
/// of one of its records set to another value.
fn damage_inside_a_chunk(b: &mut [u8], rng: &mut Rng) {
    let chunks: Vec<_> = records(b).into_iter().filter(|r| r.0 == 0x06).collect();
    if chunks.is_empty() {
        return;
    }
    let (_, at, len) = chunks[rng.below(chunks.len())];
    let body = at + 9;
    // Body: start, end, uncompressed size (8 each), CRC (4), compression (4 + n), records (8 + n).
    let compression_len =
        u32::from_le_bytes(b[body + 28..body + 32].try_into().unwrap_or_default());
    if compression_len != 0 || len < 40 {
        return;
    }
    b[body + 24..body + 28].fill(0);
    let (start, end) = (body + 40, body + len);
    let mut inner = Vec::new();
    let mut pos = start;
    while pos + 9 <= end {
        inner.push(pos + 1);
        let l = u64::from_le_bytes(b[pos + 1..pos + 9].try_into().unwrap_or_default());
        match usize::try_from(l)
            .ok()
            .and_then(|l| (pos + 9).checked_add(l))
        {
            Some(next) if next > pos && next <= end => pos = next,
            _ => break,
        }
    }
    if inner.is_empty() {
        return;
    }
    let field = inner[rng.below(inner.len())];
    let old = u64::from_le_bytes(b[field..field + 8].try_into().unwrap_or_default());
    let new = [old / 2, old.saturating_sub(1), old + 1, 0][rng.below(4)];
    b[field..field + 8].copy_from_slice(&new.to_le_bytes());
}

/// One to four mutations of `input`.
fn mutate(input: &[u8], rng: &mut Rng) -> Vec<u8> {
    let mut b = input.to_vec();
    for _ in 0..1 + rng.below(4) {
        if b.is_empty() {
            break;
        }
        match rng.below(8) {
            6 => redefine_a_channel(&mut b, rng),
            7 => damage_inside_a_chunk(&mut b, rng),
            0 => {
                let at = rng.below(b.len());
                b[at] ^= 1 << rng.below(8);
            }
            1 => {
                let at = rng.below(b.len());
                b[at] = INTERESTING[rng.below(INTERESTING.len())] as u8;
            }
            2 => b.truncate(rng.below(b.len())),
            3 => {
                // A record length field (u64) or any 4/8 bytes set to an interesting value.
                let fields = length_fields(&b);
                let (at, width) = if rng.below(2) == 0 && !fields.is_empty() {
                    (fields[rng.below(fields.len())], 8)
                } else {
                    (rng.below(b.len()), [4, 8][rng.below(2)])
                };
                let value = INTERESTING[rng.below(INTERESTING.len())].to_le_bytes();
                let end = (at + width).min(b.len());
                b[at..end].copy_from_slice(&value[..end - at]);
            }
            4 => {
                // Splice: copy a range over another place.
                let (from, to) = (rng.below(b.len()), rng.below(b.len()));
                let len = rng.below(64).min(b.len() - from).min(b.len() - to);
                let piece = b[from..from + len].to_vec();
                b[to..to + len].copy_from_slice(&piece);
            }
            _ => {
                let (at, len) = (rng.below(b.len()), rng.below(32));
                b.drain(at..(at + len).min(b.len()));
            }
        }
    }
    b
}

/// Caps the address space so that an allocation sized by a damaged length fails loudly.
fn cap_address_space(bytes: u64) {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: setrlimit on this process only, with a fully initialised struct.
    unsafe {
        let limit = libc::rlimit {
            rlim_cur: bytes,
            rlim_max: bytes,
        };
        libc::setrlimit(libc::RLIMIT_AS, &limit);
    }
}

fn arg(name: &str, default: u64) -> u64 {
    let args: Vec<String> = std::env::args().collect();
    args.iter()
        .position(|a| a == name)
        .and_then(|k| args.get(k + 1))
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn main() {
    let seconds = arg("--seconds", 60);
    let seed = arg("--seed", 1);
    let seeds = seeds();
    for s in &seeds {
        assert!(fuzz::exercise(s) > 0, "every seed recording reads");
    }
    cap_address_space(4 << 30);
    let current =
        std::env::temp_dir().join(format!("fuzz_reader_current_{}.mcap", std::process::id()));
    let mut rng = Rng(seed);
    let started = Instant::now();
    let mut cases = 0u64;
    while started.elapsed() < Duration::from_secs(seconds) {
        let input = mutate(&seeds[rng.below(seeds.len())], &mut rng);
        // Kept on disk while it runs: an abort (e.g. out of memory) leaves it to look at.
        if cases.is_multiple_of(64) || input.len() < 1 << 16 {
            let _ = std::fs::write(&current, &input);
        }
        if std::panic::catch_unwind(|| fuzz::exercise(&input)).is_err() {
            let dir =
                std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fuzz_regressions");
            let _ = std::fs::create_dir_all(&dir);
            let path = dir.join(format!("seed{seed}_case{cases}.mcap"));
            std::fs::write(&path, &input).expect("save the crashing input");
            eprintln!(
                "fuzz_reader: panic on case {cases} (seed {seed}); input saved as {}",
                path.display()
            );
            std::process::exit(1);
        }
        cases += 1;
    }
    let _ = std::fs::remove_file(&current);
    println!(
        "fuzz_reader: {cases} mutated inputs in {seconds} s (seed {seed}, {} seed recordings): no panic",
        seeds.len()
    );
}
