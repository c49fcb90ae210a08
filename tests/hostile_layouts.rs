//! Hostile input end to end, the third round: point-cloud layouts that used to lose returns
//! without a word (signed or non-finite ring values, coordinates near 1e30, a topic whose
//! layout changes, one topic in two families), absurd flags and configs that used to abort,
//! and names that are not UTF-8. Each test builds its own bad input.

mod common;
#[path = "common/hostile.rs"]
mod hostile_support;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Output;

use common::{bin, stderr};
use hostile_support::{expect_exit, json, no_temporary_files, run_limited};
use rangegan_mcap::io::decoders::Family;
use rangegan_mcap::io::encoders::{self, Kind, Payload};
use rangegan_mcap::io::pointcloud::{CloudLayout, Field, Numeric};
use rangegan_mcap::io::wire::WireReader;

/// A ring field's value for each beam.
type RingValue<'a> = &'a dyn Fn(usize) -> f64;

/// Beams and columns of the synthetic sensor: a wall 10 m away, +10 to -20 deg.
const BEAMS: usize = 32;
const COLUMNS: usize = 64;

/// The point of beam `b` (top first) at column `c`.
fn point(b: usize, c: usize) -> [f32; 3] {
    let el = (10.0 - 30.0 * b as f32 / (BEAMS - 1) as f32).to_radians();
    let az = (c as f32 + 0.5) / COLUMNS as f32 * std::f32::consts::TAU;
    let r = 10.0;
    [
        r * el.cos() * az.cos(),
        r * el.cos() * az.sin(),
        r * el.sin(),
    ]
}

/// One cloud as ROS 2 CDR: x, y, z as float32 and a ring field of type `ring` whose value
/// for beam `b` is `ring_value(b)`; `organized` lays it out beams x columns, else 1 x n.
/// `points` may replace a point's coordinates.
fn cloud(
    ring: Option<(Numeric, RingValue)>,
    organized: bool,
    points: &dyn Fn(usize, usize) -> [f32; 3],
) -> Vec<u8> {
    let mut fields = vec![
        Field {
            name: "x".into(),
            offset: 0,
            numeric: Numeric::F32,
            count: 1,
        },
        Field {
            name: "y".into(),
            offset: 4,
            numeric: Numeric::F32,
            count: 1,
        },
        Field {
            name: "z".into(),
            offset: 8,
            numeric: Numeric::F32,
            count: 1,
        },
    ];
    if let Some((numeric, _)) = &ring {
        fields.push(Field {
            name: "ring".into(),
            offset: 12,
            numeric: *numeric,
            count: 1,
        });
    }
    let step = 16u32;
    let mut data = Vec::new();
    for b in 0..BEAMS {
        for c in 0..COLUMNS {
            for v in points(b, c) {
                data.extend_from_slice(&v.to_le_bytes());
            }
            let mut tail = [0u8; 4];
            if let Some((numeric, value)) = &ring {
                let v = value(b);
                let bytes: Vec<u8> = match numeric {
                    Numeric::I8 => vec![v as i8 as u8],
                    Numeric::I32 => (v as i32).to_le_bytes().to_vec(),
                    Numeric::F32 => (v as f32).to_le_bytes().to_vec(),
                    other => panic!("no writer for {other:?}"),
                };
                tail[..bytes.len()].copy_from_slice(&bytes);
            }
            data.extend_from_slice(&tail);
        }
    }
    let (height, width) = if organized {
        (BEAMS as u32, COLUMNS as u32)
    } else {
        (1, (BEAMS * COLUMNS) as u32)
    };
    let layout = CloudLayout {
        fields,
        point_step: step,
        row_step: step * width,
        height,
        width,
        big_endian: false,
    };
    encoders::encode(
        Family::Ros2,
        1,
        "lidar",
        &Payload::Cloud {
            layout: &layout,
            data: &data,
        },
    )
}

/// Writes `messages` (topic, family, bytes), 100 ms apart, as one recording.
fn write(path: &Path, messages: &[(&str, Family, Vec<u8>)]) {
    let file = std::io::BufWriter::new(std::fs::File::create(path).unwrap());
    let mut w = mcap::WriteOptions::new().create(file).unwrap();
    let mut channels: std::collections::HashMap<(String, Family), u16> = Default::default();
    for (k, (topic, family, data)) in messages.iter().enumerate() {
        let key = (topic.to_string(), *family);
        let id = match channels.get(&key) {
            Some(&id) => id,
            None => {
                let s = encoders::schema(*family, Kind::Cloud);
                let schema = w.add_schema(&s.name, &s.encoding, &s.data).unwrap();
                let encoding = encoders::message_encoding(*family);
                let id = w
                    .add_channel(schema, topic, encoding, &BTreeMap::new())
                    .unwrap();
                channels.insert(key, id);
                id
            }
        };
        let t = 1_000_000_000 + k as u64 * 100_000_000;
        let header = mcap::records::MessageHeader {
            channel_id: id,
            sequence: k as u32,
            log_time: t,
            publish_time: t,
        };
        w.write_to_known_channel(&header, data).unwrap();
    }
    w.finish().unwrap();
}

/// `convert --quality off --json` with extra flags, under the address-space limit.
fn convert_json(input: &Path, output: &Path, flags: &[&str]) -> Output {
    hostile_support::convert(input, output, &[&["--json"], flags].concat())
}

/// A topic's mean fraction of returns that kept a pixel, and its malformed count.
fn kept(report: &serde_json::Value, topic: &str) -> (f64, u64) {
    let t = &report["report"]["topics"][topic];
    (
        t["kept_fraction"].as_f64().unwrap_or(0.0),
        t["malformed"].as_u64().unwrap_or(u64::MAX),
    )
}

fn warnings(report: &serde_json::Value) -> String {
    report["report"]["warnings"].to_string()
}

/// The pixels of every range image on `topic` of `path`.
fn range_pixels(path: &Path, topic: &str) -> Vec<f32> {
    let bytes = std::fs::read(path).unwrap();
    let mut pixels = Vec::new();
    for m in mcap::MessageStream::new(&bytes).unwrap() {
        let m = m.unwrap();
        if m.channel.topic != topic {
            continue;
        }
        let mut r = WireReader::cdr(&m.data).unwrap();
        r.header().unwrap();
        let (_h, _w) = (r.u32("height").unwrap(), r.u32("width").unwrap());
        assert_eq!(r.string("encoding").unwrap(), "32FC1");
        r.u8("is_bigendian").unwrap();
        r.u32("step").unwrap();
        let data = r.bytes("data").unwrap();
        pixels.extend(
            data.chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
        );
    }
    pixels
}

/// Rings numbered -16..15 (INT8), a ring at INT32_MIN beside 1..31 (INT32), and a float
/// ring field with NaN on one beam: no return is lost without a word. The first two keep
/// every beam (rings ordered by their values); the third names the field and takes rows
/// from elevation.
#[test]
fn signed_and_non_finite_ring_values_lose_no_return() {
    let dir = tempfile::tempdir().unwrap();
    let (input, output) = (dir.path().join("in.mcap"), dir.path().join("out.mcap"));
    let at = |b: usize, c: usize| point(b, c);
    let int8 = |b: usize| b as f64 - 16.0;
    let int32 = |b: usize| if b == 0 { i32::MIN as f64 } else { b as f64 };
    let nan = |b: usize| if b == 5 { f64::NAN } else { b as f64 };
    let cases: [(Numeric, RingValue, &str); 3] = [
        (Numeric::I8, &int8, "int8"),
        (Numeric::I32, &int32, "int32"),
        (Numeric::F32, &nan, "nan"),
    ];
    for (numeric, value, name) in cases {
        let data = cloud(Some((numeric, value)), false, &at);
        write(&input, &[("/points", Family::Ros2, data)]);
        let o = convert_json(&input, &output, &[]);
        assert_eq!(o.status.code(), Some(0), "{name}: {}", stderr(&o));
        let report = json(&o);
        let (fraction, malformed) = kept(&report, "/points");
        assert_eq!(malformed, 0, "{name}: {report}");
        assert!(fraction > 0.95, "{name}: kept {fraction}: {report}");
        let said = warnings(&report);
        assert_eq!(said.contains("non-finite"), name == "nan", "{name}: {said}");
    }
}

/// Coordinates near 1e30 beside a normal wall: no pixel of `range` is infinite or beyond
/// 2 km, `info` reports a finite range, and a warning counts the points.
#[test]
fn absurd_coordinates_never_reach_a_pixel() {
    let dir = tempfile::tempdir().unwrap();
    let (input, output) = (dir.path().join("in.mcap"), dir.path().join("out.mcap"));
    let at = |b: usize, c: usize| {
        let p = point(b, c);
        if c.is_multiple_of(8) {
            p.map(|v| v * 1e29)
        } else {
            p
        }
    };
    let ring = |b: usize| b as f64;
    write(
        &input,
        &[(
            "/points",
            Family::Ros2,
            cloud(Some((Numeric::I32, &ring)), false, &at),
        )],
    );
    let o = convert_json(&input, &output, &[]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let report = json(&o);
    assert!(warnings(&report).contains("beyond 2000 m"), "{report}");
    let pixels = range_pixels(&output, "/points/rangegan/range");
    assert!(!pixels.is_empty());
    assert!(
        pixels.iter().all(|p| p.is_finite() && *p <= 2000.0),
        "an absurd range reached a pixel"
    );
    assert!(pixels.iter().filter(|p| **p > 0.0).count() > BEAMS * COLUMNS / 2);

    let o = bin()
        .args(["info", input.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(text.contains(" m"), "{text}");
    assert!(
        !text.contains("inf"),
        "info reports a non-finite range: {text}"
    );
}

/// A topic whose first scans are organized (32 x 64) and whose later ones are not (1 x
/// 2048): each layout gets its own projection and keeps its returns.
#[test]
fn a_topic_whose_layout_changes_projects_each_layout_its_own_way() {
    let dir = tempfile::tempdir().unwrap();
    let (input, output) = (dir.path().join("in.mcap"), dir.path().join("out.mcap"));
    let at = |b: usize, c: usize| point(b, c);
    // Unorganized, and in another order than the organized scans (beams bottom first).
    let shuffled = |b: usize, c: usize| point(BEAMS - 1 - b, COLUMNS - 1 - c);
    let messages = vec![
        ("/points", Family::Ros2, cloud(None, true, &at)),
        ("/points", Family::Ros2, cloud(None, true, &at)),
        ("/points", Family::Ros2, cloud(None, false, &shuffled)),
        ("/points", Family::Ros2, cloud(None, false, &shuffled)),
    ];
    write(&input, &messages);
    let o = convert_json(&input, &output, &["--sensor", "auto"]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let report = json(&o);
    let (fraction, malformed) = kept(&report, "/points");
    assert_eq!(malformed, 0, "{report}");
    assert!(fraction > 0.9, "kept {fraction} of the returns: {report}");
}

/// One topic carried by a ROS 2 and a Foxglove channel: each family's images go to a
/// channel of that family, and the independent readers decode every message.
#[test]
fn one_topic_in_two_families_gets_a_channel_per_family() {
    let dir = tempfile::tempdir().unwrap();
    let (input, output) = (dir.path().join("in.mcap"), dir.path().join("out.mcap"));
    let scan = common::synthetic_scan(8.0, 3);
    let cloud = |family| {
        let c = rangegan_mcap::io::DecodedCloud {
            scan: scan.clone(),
            stamp_nanos: 1,
            frame_id: "lidar".into(),
            notes: Vec::new(),
        };
        encoders::encode_scan(family, &c, &[])
    };
    write(
        &input,
        &[
            ("/points", Family::Ros2, cloud(Family::Ros2)),
            ("/points", Family::Foxglove, cloud(Family::Foxglove)),
            ("/points", Family::Ros2, cloud(Family::Ros2)),
            ("/points", Family::Foxglove, cloud(Family::Foxglove)),
        ],
    );
    let o = convert_json(&input, &output, &[]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let bytes = std::fs::read(&output).unwrap();
    let summary = mcap::Summary::read(&bytes).unwrap().unwrap();
    let mut encodings: Vec<String> = summary
        .channels
        .values()
        .filter(|c| c.topic == "/points/rangegan/range")
        .map(|c| c.message_encoding.clone())
        .collect();
    encodings.sort();
    assert_eq!(encodings, ["cdr", "protobuf"]);
    // Every message on a channel is in that channel's encoding.
    for m in mcap::MessageStream::new(&bytes).unwrap() {
        let m = m.unwrap();
        if m.channel.topic != "/points/rangegan/range" {
            continue;
        }
        match m.channel.message_encoding.as_str() {
            "cdr" => assert!(WireReader::cdr(&m.data).is_ok()),
            _ => {
                use foxglove::Decode;
                foxglove::messages::RawImage::decode(m.data.as_ref()).expect("a RawImage");
            }
        }
    }
    if let Some(python) = common::python() {
        common::python_read(&python, &output);
    }
}

/// Absurd flags and configs: a clear error with the flag's or the field's name, exit 1 or
/// 2, within a 3 GiB address space, and no temporary file.
#[test]
fn absurd_flags_and_configs_are_refused_before_anything_is_sized() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let out = d.join("out.mcap");
    let out_s = out.to_str().unwrap();
    let input = d.join("in.mcap");
    common::write_recording(&input, &[Family::Ros2], 2, None);
    let in_s = input.to_str().unwrap();

    let far = d.join("far.json");
    std::fs::write(
        &far,
        r#"{"name": "far", "elevation_deg": [2.0, 0.0, -2.0], "columns": 360,
            "min_range_m": 0.5, "max_range_m": 1e308}"#,
    )
    .unwrap();
    let tilted = d.join("tilted.json");
    std::fs::write(
        &tilted,
        r#"{"name": "tilted", "elevation_deg": [1000.0, 0.0, -1000.0], "columns": 360,
            "min_range_m": 0.5, "max_range_m": 100.0}"#,
    )
    .unwrap();
    let run_dir = d.join("run");
    std::fs::create_dir_all(&run_dir).unwrap();
    std::fs::write(
        run_dir.join("config.json"),
        r#"{"generator": {"channels": [100000, 64, 32, 16, 16]}}"#,
    )
    .unwrap();
    let run_s = run_dir.to_str().unwrap();
    let sim = |sensor: &str, extra: &[&str]| {
        let mut args = vec![
            "simulate",
            "--scene",
            "1",
            "--sensor",
            sensor,
            "--scans",
            "1",
            "--physics",
            "ideal",
            "--quiet",
            out_s,
        ];
        args.extend_from_slice(extra);
        run_limited(&args)
    };
    let cases: Vec<(Output, i32, &str)> = vec![
        (sim(far.to_str().unwrap(), &[]), 1, "max_range_m"),
        (sim(tilted.to_str().unwrap(), &[]), 1, "outside -90..90"),
        (sim("vlp16", &["--columns", "1000000"]), 1, "--columns"),
        (sim("vlp16", &["--columns", "16385"]), 1, "--columns"),
        (
            run_limited(&["convert", in_s, out_s, "--mask-samples", "100000"]),
            2,
            "--mask-samples",
        ),
        (
            run_limited(&["--threads", "100000", "info", in_s]),
            2,
            "--threads",
        ),
        (
            run_limited(&["convert", in_s, out_s, "--tune-steps", "4294967297"]),
            2,
            "--tune-steps",
        ),
        (
            sim("vlp16", &["--speed-mps", "4294967297"]),
            2,
            "--speed-mps",
        ),
        (
            run_limited(&["train", run_s, "--batch", "0", "--data", "nowhere"]),
            2,
            "--batch",
        ),
        (
            run_limited(&["train", run_s, "--data", "nowhere"]),
            1,
            "generator.channels",
        ),
        (
            run_limited(&["sample", "--model", run_s, "--n", "1", out_s]),
            1,
            "generator.channels",
        ),
        (
            run_limited(&[
                "diagnose",
                "--sim",
                in_s,
                "--real",
                in_s,
                "--report",
                d.join("rep").to_str().unwrap(),
                "--real-speed-mps",
                "NaN",
            ]),
            2,
            "--real-speed-mps",
        ),
        (
            run_limited(&["segment", "train", run_s, in_s, "--batch-size", "0"]),
            2,
            "--batch-size",
        ),
    ];
    for (o, code, needle) in &cases {
        expect_exit(o, *code, needle);
    }
    assert!(!out.exists(), "no output from a refused command");
    no_temporary_files(d);
}

/// `--json info` on a path that is not UTF-8 prints JSON (the path displayed); a folder
/// convert refuses a file whose name is not UTF-8, naming it, and converts the others
/// under their own names.
#[cfg(unix)]
#[test]
fn names_that_are_not_utf8_are_kept_apart_or_refused_by_name() {
    use std::os::unix::ffi::OsStrExt;
    let dir = tempfile::tempdir().unwrap();
    let inputs = dir.path().join("in");
    std::fs::create_dir_all(&inputs).unwrap();
    let bad_a = inputs.join(std::ffi::OsStr::from_bytes(b"drive\xff.mcap"));
    let bad_b = inputs.join(std::ffi::OsStr::from_bytes(b"drive\xfe.mcap"));
    let good = inputs.join("good.mcap");
    for p in [&bad_a, &bad_b, &good] {
        common::write_recording(p, &[Family::Ros2], 2, None);
    }
    let o = bin()
        .arg("--json")
        .arg("info")
        .arg(&bad_a)
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    assert!(json(&o)["file"].as_str().unwrap().contains("drive"));

    let outputs = dir.path().join("out");
    let o = bin()
        .args(["convert", "--quality", "off"])
        .arg(&inputs)
        .arg(&outputs)
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(4), "{}", stderr(&o));
    assert!(stderr(&o).contains("not UTF-8"), "{}", stderr(&o));
    let written: Vec<PathBuf> = std::fs::read_dir(&outputs)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "mcap"))
        .collect();
    assert_eq!(written, vec![outputs.join("good.mcap")], "{written:?}");
}

/// `import` where every label file has the wrong length: an error, no empty MCAP; a
/// nested `velodyne/a/*.bin` is named, not silently left out.
#[test]
fn an_import_with_nothing_to_write_fails_and_nested_scans_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("kitti");
    std::fs::create_dir_all(data.join("velodyne/a")).unwrap();
    std::fs::create_dir_all(data.join("labels")).unwrap();
    let scan: Vec<u8> = (0..100)
        .flat_map(|k| {
            let p = [10.0f32, k as f32 * 0.1, -1.0, 0.5];
            p.into_iter().flat_map(f32::to_le_bytes).collect::<Vec<_>>()
        })
        .collect();
    for name in ["000000", "000001", "000002"] {
        std::fs::write(data.join(format!("velodyne/{name}.bin")), &scan).unwrap();
        // 99 labels for 100 points.
        std::fs::write(data.join(format!("labels/{name}.label")), vec![0u8; 99 * 4]).unwrap();
    }
    std::fs::write(data.join("velodyne/a/000003.bin"), &scan).unwrap();
    let out = dir.path().join("out.mcap");
    let o = bin().arg("import").arg(&data).arg(&out).output().unwrap();
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert!(stderr(&o).contains("none of its 3 scans"), "{}", stderr(&o));
    assert!(stderr(&o).contains("subfolders"), "{}", stderr(&o));
    assert!(!out.exists(), "an empty MCAP was written");
    no_temporary_files(dir.path());
}

/// Bytes beyond height x row_step are named in a warning, and the cloud still converts.
#[test]
fn data_beyond_the_last_point_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let (input, output) = (dir.path().join("in.mcap"), dir.path().join("out.mcap"));
    let at = |b: usize, c: usize| point(b, c);
    let ring = |b: usize| b as f64;
    let mut data = cloud(Some((Numeric::I32, &ring)), false, &at);
    // The data array is the last field but one (a trailing is_dense byte): grow it by
    // rewriting the message with 40 bytes more.
    let layout_end = data.len() - 1;
    let mut longer = data[..layout_end].to_vec();
    longer.extend_from_slice(&[0u8; 40]);
    longer.push(1);
    // The data array's length prefix sits before its bytes: patch it.
    let n = (BEAMS * COLUMNS * 16) as u32;
    let at_len = (0..longer.len() - 4)
        .rev()
        .find(|&i| longer[i..i + 4] == n.to_le_bytes())
        .unwrap();
    longer[at_len..at_len + 4].copy_from_slice(&(n + 40).to_le_bytes());
    data = longer;
    write(&input, &[("/points", Family::Ros2, data)]);
    let o = convert_json(&input, &output, &[]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let report = json(&o);
    assert!(
        warnings(&report).contains("40 bytes after the last point"),
        "{report}"
    );
    assert!(kept(&report, "/points").0 > 0.95, "{report}");
}
