//! End-to-end `convert` through the built binary: every format, every record
//! copied, output read by an independent reader, and bad input handled without
//! panics or lost data.

mod common;

use std::path::Path;

use common::*;
use rangegan_mcap::io::Family;

const FAMILIES: [Family; 3] = [Family::Ros2, Family::Ros1, Family::Foxglove];

fn hash(path: &Path) -> u32 {
    crc32fast::hash(&std::fs::read(path).unwrap())
}

/// `convert --quality off ARGS...`: these tests are about I/O and range images, not decoding.
fn convert_range_only(args: &[&str]) -> std::process::Output {
    let mut all = vec!["convert", "--quality", "off"];
    all.extend_from_slice(args);
    run(&all)
}

#[test]
fn converts_every_family_and_copies_every_record() {
    let dir = tempfile::tempdir().unwrap();
    let (input, output) = (dir.path().join("in.mcap"), dir.path().join("out.mcap"));
    let messages = write_recording(&input, &FAMILIES, 5, Some(64 * 1024));
    let before = hash(&input);
    let o = convert_range_only(&[
        input.to_str().unwrap(),
        output.to_str().unwrap(),
        "--json",
        "--quiet",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(hash(&input), before, "input must never be modified");
    let summary: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let report = &summary["report"];
    assert_eq!(report["records_in"]["messages"], messages);
    assert_eq!(report["copied"]["messages"], messages);
    assert_eq!(report["copied"]["attachments"], 1);
    assert_eq!(report["copied"]["metadata"], 1);
    assert_eq!(report["outputs_written"], 15);
    for family in FAMILIES {
        let topic = format!("/lidar_{family:?}").to_lowercase();
        let t = &report["topics"][&topic];
        assert_eq!(t["scans"], 5, "{topic}");
        assert_eq!(t["malformed"], 0);
        assert_eq!(t["strategy"], "ring-field");
        // Every return of the synthetic 16 x 360 sensor keeps its pixel.
        assert!(t["kept_fraction"].as_f64().unwrap() > 0.999, "{topic}: {t}");
    }

    if let Some(node) = node() {
        // Foxglove's own readers decode every message, protobuf RawImage included.
        let r = node_read(&node, &output);
        assert_eq!(r["decoded"], messages + 15);
        assert_eq!(
            r["images"]["/lidar_foxglove/rangegan/range"],
            serde_json::json!([16, 360, "32FC1", 1440, 16 * 1440])
        );
        assert_eq!(
            r["images"]["/lidar_ros2/rangegan/range"],
            r["images"]["/lidar_foxglove/rangegan/range"]
        );
    }
    let Some(py) = python() else { return };
    let r = python_read(&py, &output);
    let topics = &r["topics"];
    for family in FAMILIES {
        let topic = format!("/lidar_{family:?}").to_lowercase();
        assert_eq!(topics[&topic]["messages"], 5);
        assert_eq!(topics[format!("{topic}/rangegan/range")]["messages"], 5);
    }
    assert_eq!(topics["/notes"]["messages"], 5);
    assert_eq!(r["attachments"], 1);
    assert_eq!(r["metadata"]["robot"]["id"], "7");
    assert_eq!(r["metadata"]["rangegan"]["tool"], "rangegan-mcap");
    // ROS range images decode as 16 x 360 float images, one row of 360 floats per step.
    let img = &r["images"]["/lidar_ros2/rangegan/range"];
    assert_eq!(img, &serde_json::json!([16, 360, "32FC1", 1440, 16 * 1440]));
    assert_eq!(r["images"]["/lidar_ros1/rangegan/range"], *img);
    // 10 ROS point clouds + 10 ROS images decoded by the independent decoders.
    assert_eq!(r["decoded"], 20);
}

#[test]
fn refuses_to_overwrite_input_or_existing_output() {
    let dir = tempfile::tempdir().unwrap();
    let (input, output) = (dir.path().join("in.mcap"), dir.path().join("out.mcap"));
    write_recording(&input, &[Family::Ros2], 1, None);
    let i = input.to_str().unwrap();
    let o = convert_range_only(&[i, i]);
    assert_eq!(o.status.code(), Some(1));
    assert!(stderr(&o).contains("output is the input"), "{}", stderr(&o));

    std::fs::write(&output, b"keep me").unwrap();
    let o = convert_range_only(&[i, output.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(1));
    assert!(stderr(&o).contains("--force"));
    assert_eq!(std::fs::read(&output).unwrap(), b"keep me");
    let o = convert_range_only(&[i, output.to_str().unwrap(), "--force", "--quiet"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_ne!(std::fs::read(&output).unwrap(), b"keep me");
}

/// Cuts a recording at several points (as a killed recorder leaves it): every
/// complete message is processed, the tail is reported, exit 0 unless --strict.
#[test]
fn truncated_recordings_keep_every_complete_message() {
    let dir = tempfile::tempdir().unwrap();
    let full = dir.path().join("full.mcap");
    write_recording(&full, &[Family::Ros2], 20, Some(16 * 1024));
    let bytes = std::fs::read(&full).unwrap();
    let mut last = 0;
    for fraction in [0.3, 0.6, 0.9] {
        let cut = dir.path().join("cut.mcap");
        let out = dir.path().join("cut.out.mcap");
        std::fs::write(&cut, &bytes[..(bytes.len() as f64 * fraction) as usize]).unwrap();
        let o = convert_range_only(&[
            cut.to_str().unwrap(),
            out.to_str().unwrap(),
            "--json",
            "--force",
        ]);
        assert!(o.status.success(), "{}", stderr(&o));
        let err = stderr(&o);
        assert!(
            err.contains("truncated") && err.contains("could not be read"),
            "{err}"
        );
        let s: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        let scans = s["report"]["topics"]["/lidar_ros2"]["scans"]
            .as_u64()
            .unwrap();
        assert!(
            scans > last,
            "more of the file gives more scans ({scans} after {last})"
        );
        assert_eq!(
            s["report"]["copied"]["messages"],
            s["report"]["records_in"]["messages"]
        );
        assert!(s["report"]["read"]["unread_bytes"].as_u64().unwrap() > 0);
        last = scans;
        let strict = convert_range_only(&[
            cut.to_str().unwrap(),
            out.to_str().unwrap(),
            "--force",
            "--strict",
            "--quiet",
        ]);
        assert_eq!(strict.status.code(), Some(3));
    }
}

/// Flips a byte inside a compressed chunk: the chunk is named by topic and time;
/// `--on-error skip` drops it and reports the loss.
#[test]
fn corrupt_chunks_are_named_and_can_be_skipped() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("in.mcap");
    let output = dir.path().join("out.mcap");
    write_recording(&input, &[Family::Ros2], 6, Some(16 * 1024));
    let mut bytes = std::fs::read(&input).unwrap();
    // Second chunk record: opcode 0x06 found by walking the records after the header.
    let mut pos = 8;
    let mut chunks = Vec::new();
    while pos + 9 <= bytes.len() {
        let len = u64::from_le_bytes(bytes[pos + 1..pos + 9].try_into().unwrap()) as usize;
        if bytes[pos] == 0x06 {
            chunks.push((pos, len));
        }
        if bytes[pos] == 0x02 {
            break; // footer
        }
        pos += 9 + len;
    }
    assert!(chunks.len() >= 3, "fixture needs several chunks");
    let (start, len) = chunks[1];
    bytes[start + 9 + len - 10] ^= 0xff;
    std::fs::write(&input, &bytes).unwrap();

    let o = convert_range_only(&[input.to_str().unwrap(), output.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(1));
    let err = stderr(&o);
    assert!(err.contains("/lidar_ros2"), "{err}");
    assert!(
        err.contains("--on-error skip") && err.contains(" s to "),
        "{err}"
    );
    assert!(!output.exists(), "a failed conversion leaves no output");
    let leftovers: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().ends_with(".tmp"))
        .collect();
    assert!(leftovers.is_empty(), "no temporary file left behind");

    let o = convert_range_only(&[
        input.to_str().unwrap(),
        output.to_str().unwrap(),
        "--on-error",
        "skip",
        "--json",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stderr(&o).contains("skipped"), "{}", stderr(&o));
    let s: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(
        s["report"]["read"]["bad_chunks"].as_array().unwrap().len(),
        1
    );
    let lost = s["report"]["read"]["bad_chunks"][0]["messages"]
        .as_u64()
        .unwrap();
    let copied = s["report"]["copied"]["messages"].as_u64().unwrap();
    assert_eq!(
        copied + lost,
        12,
        "every input message is copied or reported lost"
    );
}

/// N good and M malformed point clouds: N scans, M warnings naming topic and
/// time, and all N + M messages copied unchanged.
#[test]
fn malformed_clouds_are_copied_and_reported() {
    use rangegan_mcap::io::decoders::DecodedCloud;
    use rangegan_mcap::io::encoders::{self, Kind};
    let dir = tempfile::tempdir().unwrap();
    let (input, output) = (dir.path().join("in.mcap"), dir.path().join("out.mcap"));
    let mut w = mcap::WriteOptions::new()
        .create(std::io::BufWriter::new(
            std::fs::File::create(&input).unwrap(),
        ))
        .unwrap();
    let s = encoders::schema(Family::Ros2, Kind::Cloud);
    let schema = w.add_schema(&s.name, &s.encoding, &s.data).unwrap();
    let ch = w
        .add_channel(schema, "/points", "cdr", &Default::default())
        .unwrap();
    for i in 0..8u64 {
        let cloud = DecodedCloud {
            scan: synthetic_scan(7.0, i as u32),
            stamp_nanos: i,
            frame_id: "l".into(),
            notes: Vec::new(),
        };
        let mut data = encoders::encode_scan(Family::Ros2, &cloud, &[]);
        if i % 3 == 1 {
            data.truncate(data.len() / 2); // data shorter than height * row_step
        }
        let h = mcap::records::MessageHeader {
            channel_id: ch,
            sequence: i as u32,
            log_time: 2_000_000_000 + i,
            publish_time: 0,
        };
        w.write_to_known_channel(&h, &data).unwrap();
    }
    w.finish().unwrap();
    drop(w);
    let o = convert_range_only(&[input.to_str().unwrap(), output.to_str().unwrap(), "--json"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let err = stderr(&o);
    assert_eq!(err.matches("warning:").count(), 3, "{err}");
    assert!(
        err.contains("/points @ 2.000000001 s") && err.contains("copied unchanged"),
        "{err}"
    );
    let s: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(s["report"]["topics"]["/points"]["scans"], 5);
    assert_eq!(s["report"]["topics"]["/points"]["malformed"], 3);
    assert_eq!(s["report"]["copied"]["messages"], 8);
    let strict = convert_range_only(&[
        input.to_str().unwrap(),
        output.to_str().unwrap(),
        "--force",
        "--strict",
        "--quiet",
    ]);
    assert_eq!(strict.status.code(), Some(3));
}

#[test]
fn not_an_mcap_is_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("notes.txt");
    std::fs::write(&input, b"hello, this is not a recording").unwrap();
    let o = convert_range_only(&[
        input.to_str().unwrap(),
        dir.path().join("o.mcap").to_str().unwrap(),
    ]);
    assert_eq!(o.status.code(), Some(1));
    assert!(
        stderr(&o).contains("notes.txt") && stderr(&o).contains("not an MCAP"),
        "{}",
        stderr(&o)
    );
}
