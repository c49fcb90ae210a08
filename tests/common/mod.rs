//! Shared helpers for end-to-end tests: synthetic recordings written with the bare
//! `mcap` crate, the built binary, and the independent Python reader.
#![allow(dead_code)]

use std::borrow::Cow;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use rangegan_mcap::io::decoders::{DecodedCloud, Family};
use rangegan_mcap::io::encoders::{self, Kind};
use rangegan_mcap::lidar::{Scan, SensorProfile};

pub fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_rangegan-mcap"))
}

pub fn run(args: &[&str]) -> Output {
    bin().args(args).output().expect("binary runs")
}

pub fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// A small synthetic 16-beam scan: a cylinder wall at `range_m`, beam `ring`
/// recorded, some rays dropped.
pub fn synthetic_scan(range_m: f32, seed: u32) -> Scan {
    let profile = SensorProfile::builtin("vlp16").unwrap().with_columns(360);
    let grid = profile.angle_grid();
    let mut scan = Scan {
        intensity: Some(Vec::new()),
        ring: Some(Vec::new()),
        ..Default::default()
    };
    for k in 0..grid.len() {
        if (k as u32)
            .wrapping_mul(2_654_435_761)
            .wrapping_add(seed)
            .is_multiple_of(10)
        {
            continue; // dropped ray
        }
        let [x, y, z] = grid.direction(k);
        scan.xyz.push([x * range_m, y * range_m, z * range_m]);
        scan.intensity.as_mut().unwrap().push((k % 256) as f32);
        scan.ring.as_mut().unwrap().push((15 - k / 360) as u16);
    }
    scan.height = 1;
    scan.width = scan.xyz.len();
    scan
}

/// Writes a recording with one point-cloud topic per family given, plus a
/// non-cloud topic, an attachment and a metadata record. Returns message count.
pub fn write_recording(
    path: &Path,
    families: &[Family],
    scans: usize,
    chunk_size: Option<u64>,
) -> u64 {
    write_recording_with(
        path,
        families,
        scans,
        chunk_size,
        Some(mcap::Compression::Zstd),
    )
}

/// Writes `scans` as one ROS 2 recording on `/points`, 100 ms apart.
pub fn write_scans(path: &Path, scans: &[Scan]) {
    rangegan_mcap::io::roundtrip::write_scans(path, "/points", "lidar", scans).unwrap();
}

/// [`write_recording`] with the chunk compression given.
pub fn write_recording_with(
    path: &Path,
    families: &[Family],
    scans: usize,
    chunk_size: Option<u64>,
    compression: Option<mcap::Compression>,
) -> u64 {
    let file = std::io::BufWriter::new(std::fs::File::create(path).unwrap());
    let opts = mcap::WriteOptions::new()
        .compression(compression)
        .chunk_size(chunk_size);
    let mut w = opts.create(file).unwrap();
    let mut channels = Vec::new();
    for family in families {
        let s = encoders::schema(*family, Kind::Cloud);
        let schema = w.add_schema(&s.name, &s.encoding, &s.data).unwrap();
        let topic = format!("/lidar_{family:?}").to_lowercase();
        let id = w
            .add_channel(
                schema,
                &topic,
                encoders::message_encoding(*family),
                &BTreeMap::new(),
            )
            .unwrap();
        channels.push((id, *family));
    }
    let note = w
        .add_channel(0, "/notes", "json", &BTreeMap::new())
        .unwrap();
    let mut count = 0;
    for i in 0..scans {
        let t = 1_000_000_000 + i as u64 * 100_000_000;
        for (id, family) in &channels {
            let cloud = DecodedCloud {
                scan: synthetic_scan(5.0 + i as f32, i as u32),
                stamp_nanos: t,
                frame_id: "lidar".into(),
                notes: Vec::new(),
            };
            let data = encoders::encode_scan(*family, &cloud, &[]);
            let header = mcap::records::MessageHeader {
                channel_id: *id,
                sequence: i as u32,
                log_time: t,
                publish_time: t,
            };
            w.write_to_known_channel(&header, &data).unwrap();
            count += 1;
        }
        let header = mcap::records::MessageHeader {
            channel_id: note,
            sequence: i as u32,
            log_time: t,
            publish_time: t,
        };
        w.write_to_known_channel(&header, format!("{{\"i\":{i}}}").as_bytes())
            .unwrap();
        count += 1;
    }
    w.attach(&mcap::Attachment {
        log_time: 1,
        create_time: 1,
        name: "calib.txt".into(),
        media_type: "text/plain".into(),
        data: Cow::Borrowed(b"P0: 1 0 0"),
    })
    .unwrap();
    w.write_metadata(&mcap::records::Metadata {
        name: "robot".into(),
        metadata: BTreeMap::from([("id".into(), "7".into())]),
    })
    .unwrap();
    w.finish().unwrap();
    count
}

/// The Python interpreter with `mcap`, `mcap-ros1-support` and `mcap-ros2-support`
/// (`.ci/run` installs them into `.venv`). `None` = not installed: the caller skips,
/// except under CI where that is an error.
pub fn python() -> Option<PathBuf> {
    let candidates = [
        std::env::var("RANGEGAN_PYTHON").ok().map(PathBuf::from),
        Some(PathBuf::from(".venv/bin/python")),
    ];
    let found = candidates.into_iter().flatten().find(|p| p.exists());
    if found.is_none() {
        assert!(
            std::env::var("CI").is_err(),
            "CI must install the Python readers (.ci/run makes .venv)"
        );
        eprintln!(
            "skipped: no .venv/bin/python with the mcap readers; run .ci/run once to install them"
        );
    }
    found
}

/// Runs `tests/py/read_mcap.py` on `path`: decodes every message with the
/// independent readers and returns its JSON report.
pub fn python_read(python: &Path, path: &Path) -> serde_json::Value {
    let out = Command::new(python)
        .arg("tests/py/read_mcap.py")
        .arg(path)
        .output()
        .expect("python runs");
    assert!(
        out.status.success(),
        "python reader failed on {}: {}",
        path.display(),
        stderr(&out)
    );
    serde_json::from_slice(&out.stdout).expect("reader prints JSON")
}

/// `node` with Foxglove's readers installed in `tests/js/node_modules` (`.ci/run`
/// runs `npm ci` there). `None` = not installed: skip, except under CI.
pub fn node() -> Option<PathBuf> {
    let ready = Path::new("tests/js/node_modules/@mcap/core").exists();
    let node = std::env::var("RANGEGAN_NODE").unwrap_or_else(|_| "node".into());
    if !ready {
        assert!(
            std::env::var("CI").is_err(),
            "CI must install the npm readers (.ci/run runs npm ci in tests/js)"
        );
        eprintln!(
            "skipped: tests/js/node_modules is missing; run .ci/run once to install Foxglove's readers"
        );
        return None;
    }
    Some(PathBuf::from(node))
}

/// Runs `tests/js/read_mcap.mjs` (@mcap/core + Foxglove's deserializers) on
/// `path`; fails the test if any message does not decode.
pub fn node_read(node: &Path, path: &Path) -> serde_json::Value {
    let out = Command::new(node)
        .arg("tests/js/read_mcap.mjs")
        .arg(path)
        .output()
        .expect("node runs");
    assert!(
        out.status.success(),
        "Foxglove readers failed on {}: {}{}",
        path.display(),
        String::from_utf8_lossy(&out.stdout),
        stderr(&out)
    );
    serde_json::from_slice(&out.stdout).expect("reader prints JSON")
}

/// Top-level records of an MCAP file as (opcode, offset, body length), header to footer.
pub fn top_level_records(bytes: &[u8]) -> Vec<(u8, usize, usize)> {
    let mut pos = 8;
    let mut records = Vec::new();
    while pos + 9 <= bytes.len() {
        let len = u64::from_le_bytes(bytes[pos + 1..pos + 9].try_into().unwrap()) as usize;
        records.push((bytes[pos], pos, len));
        if bytes[pos] == 0x02 {
            break; // footer
        }
        pos += 9 + len;
    }
    records
}

/// The real LiDAR data beside the repository (`../shared/real_lidar`, or
/// `/work/shared/real_lidar` from a worktree), or `None` with a message saying why the
/// calling test skips.
pub fn real_data(test: &str) -> Option<PathBuf> {
    const REAL: &str = "../shared/real_lidar";
    const FALLBACK: &str = "/work/shared/real_lidar";
    if let Some(dir) = [REAL, FALLBACK]
        .map(Path::new)
        .into_iter()
        .find(|d| d.is_dir())
    {
        Some(dir.to_path_buf())
    } else {
        eprintln!(
            "{test}: skipped, {REAL} is absent (real LiDAR data lives beside the repository, see its PROVENANCE.md)"
        );
        None
    }
}

/// The first file (by name) in `dir` whose name ends with `suffix`.
pub fn first_file(dir: &Path, suffix: &str) -> PathBuf {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.to_string_lossy().ends_with(suffix))
        .min()
        .unwrap()
}
