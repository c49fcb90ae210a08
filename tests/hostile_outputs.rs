//! Hostile input end to end, beyond the MCAP structure: adversarial point clouds (more
//! distinct ring values than any sensor has beams), an input topic named like an output's,
//! SemanticKITTI imports with stray or damaged files, and what the commands write: never
//! over an input, nothing temporary left after a signal or a full disk, sampled depths
//! within the model's range. Each test makes its own input; the helpers shared with
//! `tests/hostile.rs` are in `tests/common/hostile.rs`.

mod common;
#[path = "common/hostile.rs"]
mod hostile_support;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use common::{bin, run, stderr, write_recording};
use hostile_support::{
    convert, copied_messages, expect_exit, in_out, json, no_temporary_files, output_topics,
};
use rangegan_mcap::io::decoders::{DecodedCloud, Family};
use rangegan_mcap::io::encoders::{self, Kind};
use rangegan_mcap::lidar::Scan;

/// A 65 536-point cloud whose uint16 ring field holds 65 536 distinct values: the
/// message is copied and reported (no profile has that many beams) in bounded memory,
/// with and without a fixed sensor; absurd `--columns` is a clear error.
#[test]
fn distinct_ring_values_beyond_any_sensor_are_bounded_and_reported() {
    let dir = tempfile::tempdir().unwrap();
    let (input, output) = (dir.path().join("rings.mcap"), dir.path().join("out.mcap"));
    let n = 65_536usize;
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
    let mut w = mcap::Writer::new(std::io::BufWriter::new(
        std::fs::File::create(&input).unwrap(),
    ))
    .unwrap();
    let s = encoders::schema(Family::Ros2, Kind::Cloud);
    let schema = w.add_schema(&s.name, &s.encoding, &s.data).unwrap();
    let channel = w
        .add_channel(schema, "/points", "cdr", &BTreeMap::new())
        .unwrap();
    let cloud = DecodedCloud {
        scan: scan.clone(),
        stamp_nanos: 5,
        frame_id: "lidar".into(),
        notes: Vec::new(),
    };
    let data = encoders::encode_scan(Family::Ros2, &cloud, &[]);
    let header = mcap::records::MessageHeader {
        channel_id: channel,
        sequence: 0,
        log_time: 5,
        publish_time: 5,
    };
    w.write_to_known_channel(&header, &data).unwrap();
    w.finish().unwrap();
    drop(w);

    for sensor in ["auto", "hdl64e"] {
        let o = convert(&input, &output, &["--sensor", sensor, "--json"]);
        assert!(o.status.success(), "{sensor}: {}", stderr(&o));
        let s = json(&o);
        assert_eq!(copied_messages(&s), 1);
        assert_eq!(s["report"]["topics"]["/points"]["malformed"], 1, "{s}");
        let warning = s["report"]["warnings"][0]["message"]
            .as_str()
            .unwrap()
            .to_string();
        assert!(
            warning.contains("rings") || warning.contains("ring values"),
            "{warning}"
        );
    }
    let o = convert(&input, &output, &["--strict"]);
    assert_eq!(o.status.code(), Some(3));
    let o = convert(&input, &output, &["--columns", "4000000000"]);
    expect_exit(&o, 1, "give 1 to 16384 columns");
    // `render` skips such a scan with a warning and exits 0; only `--strict` makes that
    // exit 3, and then it leaves no output.
    let mixed = dir.path().join("mixed.mcap");
    let mut w = mcap::Writer::new(std::io::BufWriter::new(
        std::fs::File::create(&mixed).unwrap(),
    ))
    .unwrap();
    let schema = w.add_schema(&s.name, &s.encoding, &s.data).unwrap();
    let channel = w
        .add_channel(schema, "/points", "cdr", &BTreeMap::new())
        .unwrap();
    for (i, scan) in [common::synthetic_scan(10.0, 1), scan]
        .into_iter()
        .enumerate()
    {
        let stamp = 100_000_000 * (i as u64 + 1);
        let cloud = DecodedCloud {
            scan,
            stamp_nanos: stamp,
            frame_id: "lidar".into(),
            notes: Vec::new(),
        };
        let header = mcap::records::MessageHeader {
            channel_id: channel,
            sequence: i as u32,
            log_time: stamp,
            publish_time: stamp,
        };
        let data = encoders::encode_scan(Family::Ros2, &cloud, &[]);
        w.write_to_known_channel(&header, &data).unwrap();
    }
    w.finish().unwrap();
    drop(w);
    let rendered = dir.path().join("rendered.mcap");
    let render = |extra: &[&str]| {
        let mut args = vec![
            "render",
            "--physics",
            "ideal",
            "--sensor",
            "vlp16",
            "--force",
        ];
        args.extend_from_slice(extra);
        args.extend([mixed.to_str().unwrap(), rendered.to_str().unwrap()]);
        run(&args)
    };
    let o = render(&[]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    assert!(stderr(&o).contains("warning"), "{}", stderr(&o));
    std::fs::remove_file(&rendered).unwrap();
    let o = render(&["--strict"]);
    assert_eq!(o.status.code(), Some(3), "{}", stderr(&o));
    assert!(
        !rendered.exists(),
        "--strict keeps no output when it exits non-zero"
    );
}

/// SIGTERM and SIGINT in the middle of a conversion remove the temporary output
/// (exit 143 / 130); a temporary file left by a killed process is removed by the next
/// run writing the same output.
#[test]
fn interrupted_conversions_leave_no_temporary_file() {
    let (dir, input, output) = in_out();
    write_recording(&input, &[Family::Ros2], 40, Some(16 * 1024));
    for (signal, code) in [("TERM", 143), ("INT", 130)] {
        // Auto-decoding by the GAN (through the model, which these 16-beam scans would
        // otherwise skip) makes the run long enough to be interrupted.
        let model = concat!(env!("CARGO_MANIFEST_DIR"), "/models/dusty2");
        let mut child = bin()
            .args(["convert", "--quiet", "--threads", "1", "--decoder", "gan"])
            .args(["--model", model])
            .args([&input, &output])
            .spawn()
            .unwrap();
        let started = std::time::Instant::now();
        while !has_temporary_file(dir.path()) {
            assert!(
                started.elapsed().as_secs() < 60,
                "no temporary file appeared"
            );
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
        std::thread::sleep(std::time::Duration::from_millis(300));
        let killed = std::process::Command::new("kill")
            .args([format!("-{signal}"), child.id().to_string()])
            .status()
            .unwrap();
        assert!(killed.success());
        let status = child.wait().unwrap();
        assert_eq!(status.code(), Some(code), "SIG{signal}");
        assert!(!output.exists());
        no_temporary_files(dir.path());
    }
    // A killed run's leftover (a pid above the kernel's pid_max limit: never alive).
    let stale = dir.path().join(".out.mcap.4194305.tmp");
    std::fs::write(&stale, b"partial").unwrap();
    let o = convert(&input, &output, &[]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(!stale.exists(), "stale temporary file removed");
}

fn has_temporary_file(dir: &Path) -> bool {
    std::fs::read_dir(dir)
        .unwrap()
        .filter_map(|e| e.ok())
        .any(|e| e.file_name().to_string_lossy().ends_with(".tmp"))
}

/// `render`, `convert` (one file and dataset form) and `import` refuse to write over any
/// input, through the same path, a symlink or a hard link, with `--force`; the inputs
/// stay byte for byte.
#[test]
fn no_command_writes_over_its_inputs() {
    let dir = tempfile::tempdir().unwrap();
    let p = |name: &str| dir.path().join(name);
    let (sim, real) = (p("sim.mcap"), p("real.mcap"));
    write_recording(&sim, &[Family::Ros2], 2, None);
    write_recording(&real, &[Family::Ros2], 2, None);
    let before = (std::fs::read(&sim).unwrap(), std::fs::read(&real).unwrap());
    let model = p("model");
    std::fs::create_dir(&model).unwrap();
    let shipped = Path::new(env!("CARGO_MANIFEST_DIR")).join("models/dusty2");
    for name in ["config.json", "g_ema.bpk"] {
        std::fs::copy(shipped.join(name), model.join(name)).unwrap();
    }
    let weights = std::fs::read(model.join("g_ema.bpk")).unwrap();
    std::os::unix::fs::symlink(&sim, p("sim_link.mcap")).unwrap();
    std::fs::hard_link(&sim, p("sim_hard.mcap")).unwrap();
    let s = |path: &PathBuf| path.to_str().unwrap().to_string();
    let attempts: Vec<Vec<String>> = vec![
        vec![
            "render".into(),
            "--physics".into(),
            "ideal".into(),
            s(&sim),
            s(&sim),
        ],
        vec![
            "render".into(),
            "--raydrop".into(),
            "global".into(),
            "--real".into(),
            s(&real),
            s(&sim),
            s(&real),
        ],
        vec![
            "render".into(),
            "--physics".into(),
            "ideal".into(),
            s(&sim),
            s(&p("sim_link.mcap")),
        ],
        vec![
            "render".into(),
            "--physics".into(),
            "ideal".into(),
            s(&sim),
            s(&p("sim_hard.mcap")),
        ],
        vec!["convert".into(), s(&sim), s(&p("sim_hard.mcap"))],
        vec!["convert".into(), s(&p("sim_link.mcap")), s(&sim)],
        // A model's files are inputs too.
        vec![
            "convert".into(),
            "--model".into(),
            s(&model),
            s(&sim),
            s(&model.join("g_ema.bpk")),
        ],
        vec![
            "render".into(),
            "--raydrop".into(),
            "gan".into(),
            "--model".into(),
            s(&model),
            s(&sim),
            s(&model.join("g_ema.bpk")),
        ],
    ];
    for args in attempts {
        let o = bin().args(&args).arg("--force").output().unwrap();
        assert_eq!(o.status.code(), Some(1), "{args:?}");
        assert!(
            stderr(&o).contains("output is the input"),
            "{args:?}: {}",
            stderr(&o)
        );
    }
    assert_eq!(
        (std::fs::read(&sim).unwrap(), std::fs::read(&real).unwrap()),
        before
    );
    assert_eq!(std::fs::read(model.join("g_ema.bpk")).unwrap(), weights);
    // A diagnosis report folder holding an input under a name the report writes.
    let report = p("report");
    std::fs::create_dir(&report).unwrap();
    std::fs::copy(&sim, report.join("report.json")).unwrap();
    let o = bin()
        .args(["diagnose", "--force", "--sim"])
        .arg(report.join("report.json"))
        .arg("--real")
        .arg(&real)
        .arg("--report")
        .arg(&report)
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert!(
        stderr(&o).contains("would replace the input"),
        "{}",
        stderr(&o)
    );
    assert_eq!(std::fs::read(report.join("report.json")).unwrap(), before.0);
    // Dataset form: an output file that is a hard link of its input.
    let (inputs, outputs) = (p("inputs"), p("outputs"));
    std::fs::create_dir_all(&inputs).unwrap();
    std::fs::create_dir_all(&outputs).unwrap();
    std::fs::copy(&sim, inputs.join("a.mcap")).unwrap();
    std::fs::hard_link(inputs.join("a.mcap"), outputs.join("a.mcap")).unwrap();
    let o = bin()
        .args(["convert", "--quality", "off", "--force"])
        .args([&inputs, &outputs])
        .output()
        .unwrap();
    assert_ne!(o.status.code(), Some(0));
    assert!(stderr(&o).contains("output is the input"), "{}", stderr(&o));
    assert_eq!(std::fs::read(inputs.join("a.mcap")).unwrap(), before.0);
    let kitti = p("kitti");
    std::fs::create_dir(&kitti).unwrap();
    let scan: Vec<u8> = [1.0f32, 2.0, 0.5, 0.3]
        .iter()
        .flat_map(|f| f.to_le_bytes())
        .collect();
    std::fs::write(kitti.join("000000.bin"), &scan).unwrap();
    let o = bin()
        .args(["import", kitti.to_str().unwrap()])
        .arg(kitti.join("000000.bin"))
        .arg("--force")
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert_eq!(std::fs::read(kitti.join("000000.bin")).unwrap(), scan);
}

/// An input that already has a point-cloud topic named like one of ours: the output
/// gets no two channels of one name, and a warning says which name was chosen.
#[test]
fn an_input_topic_named_like_ours_is_not_duplicated() {
    let (_dir, input, output) = in_out();
    let mut w = mcap::Writer::new(std::io::BufWriter::new(
        std::fs::File::create(&input).unwrap(),
    ))
    .unwrap();
    let s = encoders::schema(Family::Ros2, Kind::Cloud);
    let schema = w.add_schema(&s.name, &s.encoding, &s.data).unwrap();
    for (k, topic) in ["/points", "/points/rangegan/range"].iter().enumerate() {
        let channel = w
            .add_channel(schema, topic, "cdr", &BTreeMap::new())
            .unwrap();
        let cloud = DecodedCloud {
            scan: common::synthetic_scan(6.0, k as u32),
            stamp_nanos: 9,
            frame_id: "lidar".into(),
            notes: Vec::new(),
        };
        let header = mcap::records::MessageHeader {
            channel_id: channel,
            sequence: 0,
            log_time: 9,
            publish_time: 9,
        };
        w.write_to_known_channel(&header, &encoders::encode_scan(Family::Ros2, &cloud, &[]))
            .unwrap();
    }
    w.finish().unwrap();
    drop(w);
    let o = convert(&input, &output, &["--json"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let topics = output_topics(&output);
    let mut unique = topics.clone();
    unique.dedup();
    assert_eq!(topics, unique, "two channels of one name");
    assert!(
        topics.contains(&"/points/rangegan/range~2".to_string()),
        "{topics:?}"
    );
    let warnings = json(&o)["report"]["warnings"].to_string();
    assert!(warnings.contains("/points/rangegan/range~2"), "{warnings}");
}

/// Disk full while writing: the error names OUT and the OS error, and no temporary
/// file is left. Needs a small tmpfs (mounting needs root): skipped otherwise.
#[test]
fn a_full_disk_names_the_output_and_the_os_error() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("in.mcap");
    write_recording(&input, &[Family::Ros2], 20, None);
    let full = dir.path().join("small");
    std::fs::create_dir(&full).unwrap();
    let mounted = std::process::Command::new("mount")
        .args(["-t", "tmpfs", "-o", "size=64k", "tmpfs"])
        .arg(&full)
        .output()
        .is_ok_and(|o| o.status.success());
    if !mounted {
        eprintln!(
            "a_full_disk_names_the_output_and_the_os_error: skipped, cannot mount a small tmpfs (needs root)"
        );
        return;
    }
    struct Unmount<'a>(&'a Path);
    impl Drop for Unmount<'_> {
        fn drop(&mut self) {
            let _ = std::process::Command::new("umount").arg(self.0).status();
        }
    }
    let _unmount = Unmount(&full);
    let output = full.join("out.mcap");
    let o = convert(&input, &output, &[]);
    assert_eq!(o.status.code(), Some(1));
    let err = stderr(&o);
    assert!(
        err.contains(output.to_str().unwrap()) && err.contains("No space left on device"),
        "{err}"
    );
    assert!(!err.contains(&format!("{}:", input.display())), "{err}");
    no_temporary_files(&full);
    assert!(!output.exists());
}

/// `import` reads SemanticKITTI `.label` files beside the `.bin` files, warns about a
/// label file that matches no scan and about a scan without returns.
#[test]
fn import_reads_labels_beside_scans_and_reports_what_it_leaves_out() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("seq");
    std::fs::create_dir(&data).unwrap();
    let points: Vec<[f32; 4]> = (0..64)
        .map(|k| {
            let az = 0.01 + k as f32 * 0.09;
            [10.0 * az.cos(), 10.0 * az.sin(), -1.0, 0.5]
        })
        .collect();
    let scan_bytes: Vec<u8> = points
        .iter()
        .flatten()
        .flat_map(|f| f.to_le_bytes())
        .collect();
    let labels: Vec<u8> = (0..64u32)
        .flat_map(|l| (40 + l % 3).to_le_bytes())
        .collect();
    std::fs::write(data.join("000000.bin"), &scan_bytes).unwrap();
    std::fs::write(data.join("000000.label"), &labels).unwrap();
    std::fs::write(data.join("000001.bin"), b"").unwrap();
    std::fs::write(data.join("000009.label"), &labels).unwrap();
    let output = dir.path().join("out.mcap");
    let import = |flags: &[&str], out: &Path| {
        bin()
            .arg("import")
            .args(flags)
            .args([&data, out])
            .output()
            .unwrap()
    };
    let o = import(&["--json"], &output);
    assert!(o.status.success(), "{}", stderr(&o));
    let s = json(&o);
    assert_eq!(
        (s["scans"].as_u64(), s["labelled"].as_u64()),
        (Some(1), Some(1)),
        "{s}"
    );
    let warnings = s["warnings"].to_string();
    assert!(
        warnings.contains("000009.label") && warnings.contains("000001.bin"),
        "{warnings}"
    );
    let cloud = first_cloud(&output);
    assert_eq!(cloud.scan.label.unwrap()[..3], [40, 41, 42]);
    // A scan of an odd size costs only itself; --strict leaves no output and exits 3.
    std::fs::write(data.join("000002.bin"), &scan_bytes[..30]).unwrap();
    let o = import(&["--json", "--force"], &output);
    assert!(o.status.success(), "{}", stderr(&o));
    let s = json(&o);
    assert_eq!(
        (s["scans"].as_u64(), s["unreadable"].as_u64()),
        (Some(1), Some(1)),
        "{s}"
    );
    assert!(s["warnings"].to_string().contains("000002.bin"), "{s}");
    let strict = dir.path().join("strict.mcap");
    let o = import(&["--strict"], &strict);
    assert_eq!(o.status.code(), Some(3), "{}", stderr(&o));
    assert!(stderr(&o).contains("000002.bin"), "{}", stderr(&o));
    assert!(!strict.exists());
}

/// The first message of a recording, decoded as a ROS 2 point cloud.
fn first_cloud(path: &Path) -> rangegan_mcap::io::DecodedCloud {
    let bytes = std::fs::read(path).unwrap();
    let message = mcap::MessageStream::new(&bytes)
        .unwrap()
        .next()
        .unwrap()
        .unwrap();
    rangegan_mcap::io::decode_cloud(rangegan_mcap::io::CloudFormat::Ros2Cdr, &message.data).unwrap()
}

/// Real KITTI drive_a at 4.2 s ends with a lone point at azimuth exactly 0: `import`
/// writes 64 rings for it, not 65.
#[test]
fn import_writes_64_rings_for_every_real_kitti_scan() {
    let Some(real) = common::real_data("import_writes_64_rings_for_every_real_kitti_scan") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("drive");
    std::fs::create_dir(&data).unwrap();
    std::os::unix::fs::symlink(
        std::fs::canonicalize(real.join("kitti_raw_drive_a/0000000042.bin")).unwrap(),
        data.join("0000000042.bin"),
    )
    .unwrap();
    let output = dir.path().join("out.mcap");
    let o = bin()
        .args(["import", "--quiet"])
        .args([&data, &output])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let cloud = first_cloud(&output);
    assert_eq!(cloud.scan.ring.unwrap().iter().max(), Some(&63));
}

/// `sample` keeps every depth in the model's 1.45-80 m, as `convert` does.
#[test]
fn sampled_depths_stay_within_the_model_range() {
    let dir = tempfile::tempdir().unwrap();
    let output = dir.path().join("samples.mcap");
    let o = bin()
        .args(["sample", "--quiet", "--n", "2", "--seed", "3"])
        .arg(&output)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    let bytes = std::fs::read(&output).unwrap();
    let mut depths = 0;
    for message in mcap::MessageStream::new(&bytes).unwrap() {
        let message = message.unwrap();
        if !message.channel.topic.ends_with("/depth") {
            continue;
        }
        let mut r = rangegan_mcap::io::wire::WireReader::cdr(&message.data).unwrap();
        r.header().unwrap();
        let (_h, _w) = (r.u32("height").unwrap(), r.u32("width").unwrap());
        r.string("encoding").unwrap();
        r.u8("is_bigendian").unwrap();
        r.u32("step").unwrap();
        let data = r.bytes("data").unwrap();
        for v in data.chunks_exact(4) {
            let d = f32::from_le_bytes(v.try_into().unwrap());
            assert!((1.45..=80.0 + 1e-3).contains(&d), "depth {d}");
        }
        depths += 1;
    }
    assert_eq!(depths, 2);
}
