//! Hostile input end to end: each test makes a kind of damaged or adversarial input
//! itself (valid MCAPs written with the `mcap` crate, then corrupted) and checks the
//! commands neither crash nor run away with memory, recover what a careful reader can,
//! name what was skipped, and never touch an input.
//!
//! This file: damage to the MCAP structure (chunks, records, the summary section,
//! truncation, declared lengths) and the fuzzer's regressions. Adversarial point clouds,
//! imports and what the commands write are in `tests/hostile_outputs.rs`; the helpers both
//! share are in `tests/common/hostile.rs`.

mod common;
#[path = "common/hostile.rs"]
mod hostile_support;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use common::{stderr, top_level_records, write_recording_with};
use hostile_support::{
    convert, copied_messages, expect_exit, in_out, json, no_temporary_files, output_topics,
    run_limited,
};
use rangegan_mcap::io::decoders::Family;

const CHUNK: u8 = 0x06;
const CHANNEL: u8 = 0x04;
const CHUNK_INDEX: u8 = 0x08;
const DATA_END: u8 = 0x0f;

fn lost_in_chunks(report: &serde_json::Value) -> u64 {
    report["report"]["read"]["bad_chunks"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["messages"].as_u64().unwrap())
        .sum()
}

fn chunks(bytes: &[u8]) -> Vec<(usize, usize)> {
    top_level_records(bytes)
        .into_iter()
        .filter(|r| r.0 == CHUNK)
        .map(|r| (r.1, r.2))
        .collect()
}

/// Writes a recording (ROS 2 clouds + a JSON note per scan) and returns its bytes.
fn recording(path: &Path, scans: usize, compression: Option<mcap::Compression>) -> (Vec<u8>, u64) {
    let total = write_recording_with(path, &[Family::Ros2], scans, Some(16 * 1024), compression);
    (std::fs::read(path).unwrap(), total)
}

/// A chunk declaring an uncompressed size near 2^50 (one flipped bit) or 2^31 + size,
/// zstd and lz4: a named bad chunk under a 3 GiB address-space limit, skipped with
/// `--on-error skip`, for `convert` and `info`; no temporary file is left.
#[test]
fn huge_declared_chunk_sizes_are_refused_before_allocating() {
    let (dir, input, output) = in_out();
    for compression in [mcap::Compression::Zstd, mcap::Compression::Lz4] {
        for (byte, bit) in [(6, 0x04), (3, 0x80)] {
            let (mut bytes, total) = recording(&input, 4, Some(compression));
            let (offset, _) = chunks(&bytes)[1];
            // Chunk body: start time, end time, then the uncompressed size (u64).
            bytes[offset + 9 + 16 + byte] ^= bit;
            std::fs::write(&input, &bytes).unwrap();

            let o = convert(&input, &output, &[]);
            assert_eq!(o.status.code(), Some(1), "{compression:?}: {}", stderr(&o));
            let err = stderr(&o);
            assert!(
                err.contains(&format!("offset {offset}")) && err.contains("--on-error skip"),
                "{err}"
            );
            assert!(!output.exists());
            no_temporary_files(dir.path());

            let o = convert(&input, &output, &["--on-error", "skip", "--json"]);
            assert!(o.status.success(), "{compression:?}: {}", stderr(&o));
            let s = json(&o);
            assert_eq!(copied_messages(&s) + lost_in_chunks(&s), total);

            let o = run_limited(&["info", input.to_str().unwrap()]);
            assert!(o.status.success(), "{}", stderr(&o));
            std::fs::remove_file(&output).unwrap();
        }
    }
}

/// The first chunk (the only one holding the cloud channel's schema and channel
/// records) is corrupt: with `--on-error skip`, the summary section's copies resolve
/// the later chunks' messages; every message is copied or reported lost.
#[test]
fn schemas_lost_with_a_chunk_come_from_the_summary() {
    let (_dir, input, output) = in_out();
    let (mut bytes, total) = recording(&input, 6, Some(mcap::Compression::Zstd));
    let (offset, len) = chunks(&bytes)[0];
    bytes[offset + 9 + len - 10] ^= 0xff;
    std::fs::write(&input, &bytes).unwrap();
    let o = convert(&input, &output, &["--on-error", "skip", "--json"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let s = json(&o);
    assert_eq!(s["report"]["copied"]["orphan_messages"], 0, "{s}");
    assert_eq!(copied_messages(&s) + lost_in_chunks(&s), total);
    assert!(
        s["report"]["topics"]["/lidar_ros2"]["scans"]
            .as_u64()
            .unwrap()
            >= 5,
        "{s}"
    );
    assert!(
        s["report"]["read"]["from_summary"]
            .as_array()
            .unwrap()
            .len()
            >= 2,
        "{s}"
    );
    assert!(output_topics(&output).contains(&"/lidar_ros2".to_string()));
}

/// One damaged chunk-index record in the summary section: named with its offset,
/// every message still copied (the data section is enough); `--strict` exits 3 and
/// leaves no output.
#[test]
fn a_damaged_summary_record_is_named_and_loses_nothing() {
    let (_dir, input, output) = in_out();
    let (mut bytes, total) = recording(&input, 4, Some(mcap::Compression::Zstd));
    let records = top_level_records(&bytes);
    let data_end = records.iter().position(|r| r.0 == DATA_END).unwrap();
    let (_, offset, _) = *records[data_end..]
        .iter()
        .find(|r| r.0 == CHUNK_INDEX)
        .unwrap();
    // Chunk index body: 4 u64s, then the byte length of the message index offsets.
    bytes[offset + 9 + 32..offset + 9 + 36].copy_from_slice(&u32::MAX.to_le_bytes());
    std::fs::write(&input, &bytes).unwrap();
    let o = convert(&input, &output, &["--json"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let s = json(&o);
    assert_eq!(copied_messages(&s), total);
    let bad = &s["report"]["read"]["bad_records"][0];
    assert_eq!(bad["offset"], offset as u64, "{s}");
    assert!(
        bad["record"].as_str().unwrap().contains("chunk index"),
        "{s}"
    );
    let o = convert(&input, &output, &["--strict"]);
    expect_exit(&o, 3, &format!("offset {offset}"));
    assert!(
        !output.exists(),
        "--strict keeps no output when it exits non-zero"
    );
}

/// A chunk header whose compression-name length or records length is damaged: that
/// chunk is named (offset, error) and, with `--on-error skip`, skipped alone.
#[test]
fn a_damaged_chunk_header_costs_only_that_chunk() {
    let (_dir, input, output) = in_out();
    // Chunk body: 3 u64s, CRC u32, compression (u32 length + "zstd"), records length u64.
    for (field, value) in [(28usize, 0xffff_ff00u64), (36, 1 << 40)] {
        let (mut bytes, total) = recording(&input, 6, Some(mcap::Compression::Zstd));
        let (offset, _) = chunks(&bytes)[2];
        let at = offset + 9 + field;
        let width = if field == 28 { 4 } else { 8 };
        bytes[at..at + width].copy_from_slice(&value.to_le_bytes()[..width]);
        std::fs::write(&input, &bytes).unwrap();
        let o = convert(&input, &output, &[]);
        expect_exit(&o, 1, &format!("offset {offset}"));
        let o = convert(&input, &output, &["--on-error", "skip", "--json"]);
        assert!(o.status.success(), "{}", stderr(&o));
        let s = json(&o);
        assert_eq!(
            s["report"]["read"]["bad_chunks"].as_array().unwrap().len(),
            1
        );
        assert_eq!(copied_messages(&s) + lost_in_chunks(&s), total, "{s}");
    }
}

/// Damaged framing with an intact summary: the chunk index (CRC-checked) knows where every
/// chunk starts and how long it is, and reading recovers what a careful indexed reader does.
/// - A chunk in the middle of a 20-chunk file claims 2^62 bytes: it is read by the index's
///   length, all 20 scans come out, the repair is named, nothing counts as lost.
/// - The record before a chunk claims 100 bytes too many, swallowing the chunk's start:
///   reading resumes at that chunk (behind where framing broke), all 20 scans come out, and
///   the broken record is named: `--strict` exits 3 without output, and without
///   `--on-error skip` the run fails.
#[test]
fn damaged_record_lengths_are_recovered_through_the_chunk_index() {
    let (_dir, input, output) = in_out();
    let (pristine, total) = recording(&input, 20, Some(mcap::Compression::Zstd));
    let all = chunks(&pristine);
    assert!(all.len() >= 20, "{} chunks", all.len());
    let (offset, _) = all[all.len() / 2];

    let mut bytes = pristine.clone();
    bytes[offset + 1..offset + 9].copy_from_slice(&(1u64 << 62).to_le_bytes());
    std::fs::write(&input, &bytes).unwrap();
    for flags in [vec!["--json"], vec!["--json", "--strict"]] {
        let o = convert(&input, &output, &flags);
        assert!(o.status.success(), "{flags:?}: {}", stderr(&o));
        let s = json(&o);
        assert_eq!(s["report"]["topics"]["/lidar_ros2"]["scans"], 20, "{s}");
        assert_eq!(copied_messages(&s), total, "{s}");
        let repaired = s["report"]["read"]["repaired"].to_string();
        assert!(repaired.contains(&format!("offset {offset}")), "{s}");
        assert!(
            s["report"]["read"]["bad_records"]
                .as_array()
                .unwrap()
                .is_empty(),
            "{s}"
        );
    }

    let records = top_level_records(&pristine);
    let before = records
        .iter()
        .position(|r| r.1 == offset)
        .map(|i| records[i - 1])
        .unwrap();
    let mut bytes = pristine.clone();
    let swallowing = (before.2 as u64 + 100).to_le_bytes();
    bytes[before.1 + 1..before.1 + 9].copy_from_slice(&swallowing);
    std::fs::write(&input, &bytes).unwrap();
    let o = convert(&input, &output, &["--on-error", "skip", "--json"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let s = json(&o);
    assert_eq!(s["report"]["topics"]["/lidar_ros2"]["scans"], 20, "{s}");
    assert_eq!(copied_messages(&s), total, "{s}");
    let bad = s["report"]["read"]["bad_records"].to_string();
    assert!(bad.contains(&format!("chunk at offset {offset}")), "{s}");
    assert!(s["report"]["read"]["stopped"].is_null(), "{s}");
    let o = convert(&input, &output, &["--on-error", "skip", "--strict"]);
    assert_eq!(o.status.code(), Some(3));
    assert!(!output.exists());
    let o = convert(&input, &output, &[]);
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
}

/// A channel naming a schema that is nowhere in the file: its messages are copied on a
/// channel without schema, with a warning naming the topic.
#[test]
fn a_channel_with_a_missing_schema_is_copied_with_a_warning() {
    let (_dir, input, output) = in_out();
    let mut w = mcap::WriteOptions::new()
        .use_chunks(false)
        .create(std::io::BufWriter::new(
            std::fs::File::create(&input).unwrap(),
        ))
        .unwrap();
    let schema = w.add_schema("custom/Thing", "jsonschema", b"{}").unwrap();
    let channel = w
        .add_channel(schema, "/things", "json", &BTreeMap::new())
        .unwrap();
    for t in 0..3u64 {
        let header = mcap::records::MessageHeader {
            channel_id: channel,
            sequence: t as u32,
            log_time: t,
            publish_time: t,
        };
        w.write_to_known_channel(&header, b"{}").unwrap();
    }
    w.finish().unwrap();
    drop(w);
    let mut bytes = std::fs::read(&input).unwrap();
    let records = top_level_records(&bytes);
    // The schema record (in the data section and the summary) is lost: opcode 0xff is
    // an unknown record, which readers skip; the channel keeps naming schema `schema`.
    for (op, offset, _) in &records {
        if *op == 0x03 {
            bytes[*offset] = 0xff;
        }
    }
    assert!(records.iter().any(|r| r.0 == CHANNEL));
    std::fs::write(&input, &bytes).unwrap();
    let o = convert(&input, &output, &["--json"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let s = json(&o);
    assert_eq!(copied_messages(&s), 3, "{s}");
    let warnings = s["report"]["warnings"].to_string();
    assert!(
        warnings.contains("/things") && warnings.contains(&format!("schema {schema}")),
        "{warnings}"
    );
    assert!(output_topics(&output).contains(&"/things".to_string()));
}

/// A file cut inside its first chunk: a warning says nothing could be read, exit 0;
/// `--strict` exits 3 and leaves no file at OUT. The same for a file cut later; a file
/// cut before its first record is no MCAP (exit 1).
#[test]
fn unreadable_and_truncated_inputs_under_strict_leave_no_output() {
    let (dir, input, output) = in_out();
    let (bytes, _) = recording(&input, 6, Some(mcap::Compression::Zstd));
    let (first, _) = chunks(&bytes)[0];
    std::fs::write(&input, &bytes[..first + 200]).unwrap();
    let o = convert(&input, &output, &[]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(
        stderr(&o).contains("no message could be read"),
        "{}",
        stderr(&o)
    );
    std::fs::remove_file(&output).unwrap();
    for cut in [0, 5, 12] {
        std::fs::write(&input, &bytes[..cut]).unwrap();
        expect_exit(&convert(&input, &output, &[]), 1, "not an MCAP file");
    }
    for cut in [first + 200, bytes.len() * 2 / 3] {
        std::fs::write(&input, &bytes[..cut]).unwrap();
        let o = convert(&input, &output, &["--strict"]);
        assert_eq!(o.status.code(), Some(3), "{}", stderr(&o));
        assert!(
            !output.exists(),
            "--strict keeps no output when it exits non-zero"
        );
        no_temporary_files(dir.path());
    }
}

#[path = "common/fuzz.rs"]
mod fuzz;

/// Every input the fuzzer (`examples/fuzz_reader.rs`) ever crashed on reads without a
/// panic now, through the reader, the decoders, estimation and projection.
#[test]
fn fuzz_regressions_read_without_panic() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fuzz_regressions");
    let mut inputs: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap()
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "mcap"))
        .collect();
    inputs.sort();
    assert!(
        !inputs.is_empty(),
        "the regression corpus is in {}",
        dir.display()
    );
    for input in inputs {
        let bytes = std::fs::read(&input).unwrap();
        let result = std::panic::catch_unwind(|| fuzz::exercise(&bytes));
        assert!(result.is_ok(), "{} panics", input.display());
    }
}

/// `render` and `diagnose` stop at a damaged chunk (they have no `--on-error`): the error
/// names the file and gives a repair command, and that command's output is read.
#[test]
fn strict_readers_give_a_repair_command_that_works() {
    let (dir, input, output) = in_out();
    let (mut bytes, _) = recording(&input, 4, Some(mcap::Compression::Zstd));
    let (offset, _) = chunks(&bytes)[1];
    bytes[offset + 9 + 16 + 6] ^= 0x04; // an absurd declared uncompressed size
    std::fs::write(&input, &bytes).unwrap();
    let render = |sim: &Path| {
        run_limited(&[
            "render",
            "--physics",
            "realistic",
            sim.to_str().unwrap(),
            output.to_str().unwrap(),
        ])
    };
    let o = render(&input);
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    let err = stderr(&o);
    let repair = "convert --on-error skip --channels range";
    assert!(
        err.contains(&input.display().to_string()) && err.contains(repair),
        "{err}"
    );
    assert!(!err.contains("use --on-error skip"), "{err}");
    assert!(!output.exists());

    let repaired = dir.path().join("repaired.mcap");
    let o = convert(
        &input,
        &repaired,
        &["--on-error", "skip", "--channels", "range"],
    );
    assert!(o.status.success(), "{}", stderr(&o));
    let o = render(&repaired);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(output.exists());
}
