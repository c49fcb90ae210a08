//! `info`, `import` and `sample` through the built binary.

mod common;

use std::path::Path;

use common::*;
use rangegan_mcap::io::Family;

#[test]
fn info_lists_channels_counts_and_cloud_layouts() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("in.mcap");
    write_recording(&input, &[Family::Ros2, Family::Foxglove], 3, None);
    let o = run(&["info", input.to_str().unwrap(), "--json"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let channels = v["channels"].as_array().unwrap();
    assert_eq!(channels.len(), 3);
    let by_topic = |t: &str| channels.iter().find(|c| c["topic"] == t).unwrap().clone();
    assert_eq!(by_topic("/lidar_ros2")["point_cloud"], "ros2_cdr");
    assert_eq!(
        by_topic("/lidar_foxglove")["point_cloud"],
        "foxglove_protobuf"
    );
    assert!(by_topic("/notes")["point_cloud"].is_null());
    assert_eq!(by_topic("/notes")["messages"], 3);
    let layout = &by_topic("/lidar_ros2")["layout"];
    assert_eq!(layout["strategy"], "ring-field");
    assert_eq!(layout["beams"], 16);
    assert_eq!(v["attachments"].as_array().unwrap().len(), 1);
    assert_eq!(v["complete"], true);

    let text = run(&["info", input.to_str().unwrap()]);
    let out = String::from_utf8_lossy(&text.stdout);
    assert!(
        out.contains("/lidar_ros2") && out.contains("projection ring-field"),
        "{out}"
    );
}

fn write_bin(path: &Path, points: &[[f32; 4]]) {
    let bytes: Vec<u8> = points
        .iter()
        .flatten()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    std::fs::write(path, bytes).unwrap();
}

/// A synthetic KITTI folder: two rings per scan, stored ring after ring.
#[test]
fn import_writes_ros2_clouds_with_ring_and_label() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("seq");
    std::fs::create_dir_all(root.join("velodyne")).unwrap();
    std::fs::create_dir_all(root.join("labels")).unwrap();
    for s in 0..3 {
        let mut pts = Vec::new();
        for ring in 0..2 {
            for k in 0..100 {
                let az = 0.01 + k as f32 * std::f32::consts::TAU / 100.0;
                let el = if ring == 0 { 0.0f32 } else { -0.1 };
                pts.push([
                    10.0 * el.cos() * az.cos(),
                    10.0 * el.cos() * az.sin(),
                    10.0 * el.sin(),
                    0.5,
                ]);
            }
        }
        write_bin(&root.join(format!("velodyne/{s:06}.bin")), &pts);
        let labels: Vec<u8> = (0..pts.len() as u32)
            .flat_map(|i| (40 + i % 2).to_le_bytes())
            .collect();
        std::fs::write(root.join(format!("labels/{s:06}.label")), labels).unwrap();
    }
    let out = dir.path().join("seq.mcap");
    let o = run(&[
        "import",
        root.to_str().unwrap(),
        out.to_str().unwrap(),
        "--json",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(
        (v["scans"].as_u64(), v["labelled"].as_u64()),
        (Some(3), Some(3))
    );

    // Read back through our decoder: ring ids from the ring order, labels kept.
    let bytes = std::fs::read(&out).unwrap();
    let mut clouds = Vec::new();
    for m in mcap::MessageStream::new(&bytes).unwrap() {
        let m = m.unwrap();
        assert_eq!(m.channel.topic, "/velodyne_points");
        clouds.push(
            rangegan_mcap::io::decode_cloud(rangegan_mcap::io::CloudFormat::Ros2Cdr, &m.data)
                .unwrap(),
        );
        // A folder without times of its own starts at 2020-01-01 00:00:00 UTC, at 10 Hz.
        let start = 1_577_836_800_000_000_000u64;
        assert_eq!(
            m.log_time,
            start + (clouds.len() as u64 - 1) * 100_000_000,
            "10 Hz"
        );
    }
    assert_eq!(clouds.len(), 3);
    let scan = &clouds[0].scan;
    assert_eq!(scan.len(), 200);
    assert_eq!(scan.ring.as_ref().unwrap()[..2], [0, 0]);
    assert_eq!(scan.ring.as_ref().unwrap()[199], 1);
    assert_eq!(scan.label.as_ref().unwrap()[..2], [40, 41]);

    if let Some(py) = python() {
        let r = python_read(&py, &out);
        assert_eq!(r["decoded"], 3);
    }
}

#[test]
fn import_of_an_empty_folder_is_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let o = run(&[
        "import",
        dir.path().to_str().unwrap(),
        dir.path().join("o.mcap").to_str().unwrap(),
    ]);
    assert_eq!(o.status.code(), Some(1));
    assert!(
        stderr(&o).contains("no scans (expected KITTI velodyne/*.bin"),
        "{}",
        stderr(&o)
    );
    assert!(!dir.path().join("o.mcap").exists());
}

/// A one-scan KITTI folder for `import`'s input checks.
fn one_scan_folder(root: &Path) {
    std::fs::create_dir_all(root.join("velodyne")).unwrap();
    write_bin(
        &root.join("velodyne/000000.bin"),
        &[[5.0, 0.0, 0.0, 0.5], [0.0, 5.0, -1.0, 0.5]],
    );
}

#[test]
fn import_stamps_a_kitti_drive_with_its_own_time() {
    let dir = tempfile::tempdir().unwrap();
    let seq = dir.path().join("drive");
    one_scan_folder(&seq);
    std::fs::write(
        seq.join("timestamps.txt"),
        "2011-09-26 13:10:51.158069617\n2011-09-26 13:10:51.261567322\n",
    )
    .unwrap();
    let out = dir.path().join("o.mcap");
    let o = run(&["import", seq.to_str().unwrap(), out.to_str().unwrap()]);
    assert!(o.status.success(), "{}", stderr(&o));
    let bytes = std::fs::read(&out).unwrap();
    let m = mcap::MessageStream::new(&bytes)
        .unwrap()
        .next()
        .unwrap()
        .unwrap();
    let expected = 1_317_042_651_158_069_617i128;
    assert!(
        (m.log_time as i128 - expected).abs() < 1_000,
        "{}",
        m.log_time
    );
}

#[test]
fn import_refuses_start_times_a_ros_stamp_cannot_hold() {
    let dir = tempfile::tempdir().unwrap();
    one_scan_folder(&dir.path().join("seq"));
    let out = dir.path().join("o.mcap");
    for bad in ["3000000000", "20000000000", "-1", "inf"] {
        let o = run(&[
            "import",
            dir.path().join("seq").to_str().unwrap(),
            out.to_str().unwrap(),
            &format!("--start-secs={bad}"),
        ]);
        assert_ne!(o.status.code(), Some(0), "{bad}");
        assert!(stderr(&o).contains("--start-secs"), "{bad}: {}", stderr(&o));
        assert!(!out.exists(), "{bad}: no output is left behind");
    }
    let o = run(&[
        "import",
        dir.path().join("seq").to_str().unwrap(),
        out.to_str().unwrap(),
        "--start-secs",
        "2000000000",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
}

/// A FIFO named like a scan would block a reader forever; `import` passes it by, and it
/// takes `*.BIN` as well as `*.bin`.
#[cfg(unix)]
#[test]
fn import_skips_fifos_and_reads_upper_case_extensions() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("seq");
    one_scan_folder(&root);
    std::fs::rename(
        root.join("velodyne/000000.bin"),
        root.join("velodyne/000000.BIN"),
    )
    .unwrap();
    let fifo = root.join("velodyne/000001.bin");
    let made = std::process::Command::new("mkfifo")
        .arg(&fifo)
        .status()
        .unwrap();
    assert!(made.success());
    let o = run(&[
        "import",
        root.to_str().unwrap(),
        dir.path().join("o.mcap").to_str().unwrap(),
        "--json",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(v["scans"].as_u64(), Some(1), "{v}");
}

/// Every file of a model folder is an input: `sample --force` into the folder is refused.
#[test]
fn sample_never_writes_into_its_model_folder() {
    let dir = tempfile::tempdir().unwrap();
    let model = dir.path().join("model");
    let shipped = Path::new(env!("CARGO_MANIFEST_DIR")).join("models/dusty2");
    std::fs::create_dir_all(&model).unwrap();
    for f in ["config.json", "g_ema.bpk"] {
        std::fs::copy(shipped.join(f), model.join(f)).unwrap();
    }
    let weights = std::fs::read(model.join("g_ema.bpk")).unwrap();
    for target in ["g_ema.bpk", "new.mcap"] {
        let o = run(&[
            "sample",
            "--n",
            "1",
            "--force",
            "--model",
            model.to_str().unwrap(),
            model.join(target).to_str().unwrap(),
        ]);
        assert_eq!(o.status.code(), Some(1), "{target}: {}", stderr(&o));
        assert!(
            stderr(&o).contains("inputs are never modified"),
            "{}",
            stderr(&o)
        );
    }
    assert_eq!(std::fs::read(model.join("g_ema.bpk")).unwrap(), weights);
    assert!(!model.join("new.mcap").exists());
}

#[test]
fn sample_counts_are_bounded() {
    let dir = tempfile::tempdir().unwrap();
    for bad in ["18446744073709551615", "0", "100001"] {
        let o = run(&[
            "sample",
            "--n",
            bad,
            dir.path().join("s.mcap").to_str().unwrap(),
        ]);
        assert_eq!(o.status.code(), Some(2), "{bad}: {}", stderr(&o));
        assert!(stderr(&o).contains("--n"), "{bad}: {}", stderr(&o));
    }
}

/// A GPU backend this build lacks stops `train` and `train-encoder` before
/// anything is read or written, naming the cargo feature to build with.
#[cfg(not(feature = "cuda"))]
#[test]
fn training_on_a_backend_missing_from_the_build_is_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    for command in ["train", "train-encoder"] {
        let run_dir = dir.path().join(command);
        let o = run(&[
            command,
            run_dir.to_str().unwrap(),
            "--data",
            dir.path().to_str().unwrap(),
            "--backend",
            "cuda",
        ]);
        assert_eq!(o.status.code(), Some(1), "{command}");
        assert!(
            stderr(&o).contains("--features cuda"),
            "{command}: {}",
            stderr(&o)
        );
        assert!(!run_dir.exists(), "{command} wrote its run directory");
    }
}

/// `train --widen-from` refuses what is not a training run, and a narrower
/// generator, before it writes anything; `--channels` alone is a usage error.
#[test]
fn widening_refuses_a_model_directory_and_a_narrower_generator() {
    let dir = tempfile::tempdir().unwrap();
    let run_dir = dir.path().join("wide");
    let widen = |source: &str, channels: &str| {
        run(&[
            "train",
            run_dir.to_str().unwrap(),
            "--data",
            dir.path().to_str().unwrap(),
            "--widen-from",
            source,
            "--channels",
            channels,
        ])
    };
    for (source, channels, why) in [
        (
            "models/dusty2",
            "256,128,64,32,32",
            "no training checkpoint",
        ),
        ("models/gan-run", "64,64,32,16,16", "cannot remove channels"),
    ] {
        let o = widen(source, channels);
        assert_eq!(o.status.code(), Some(1), "{source}: {}", stderr(&o));
        assert!(stderr(&o).contains(why), "{source}: {}", stderr(&o));
    }
    assert!(
        !run_dir.exists(),
        "a refused widening wrote its run directory"
    );
    let o = run(&["train", run_dir.to_str().unwrap(), "--channels", "8,8"]);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
}

/// Real SemanticKITTI through import and convert: the sensor is estimated from the
/// data (64 beams by ring, columns from the azimuth step of these every-4th-point
/// files) and nearly every point keeps a pixel.
#[test]
fn real_semantickitti_imports_and_converts() {
    let Some(real) = real_data("real_semantickitti_imports_and_converts") else {
        return;
    };
    let seq = real.join("semantickitti_mini/00");
    let dir = tempfile::tempdir().unwrap();
    let (mcap, out) = (dir.path().join("00.mcap"), dir.path().join("00.out.mcap"));
    assert!(
        run(&[
            "import",
            seq.to_str().unwrap(),
            mcap.to_str().unwrap(),
            "--quiet"
        ])
        .status
        .success()
    );
    let o = run(&[
        "convert",
        "--quality",
        "off",
        mcap.to_str().unwrap(),
        out.to_str().unwrap(),
        "--json",
        "--quiet",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let t = &v["report"]["topics"]["/velodyne_points"];
    assert_eq!(t["scans"], 10);
    assert_eq!(t["rows"], 64);
    assert_eq!(t["strategy"], "ring-field");
    assert_eq!(t["sensor"], "auto");
    let columns = t["columns"].as_u64().unwrap();
    assert!(
        (500..=600).contains(&columns),
        "~502 points per ring: {columns} columns"
    );
    let kept = t["kept_fraction"].as_f64().unwrap();
    assert!(kept > 0.97, "kept {kept}");
}

/// `sample` writes the shipped model's scans as images and clouds that Foxglove's readers and
/// the Python readers decode, in both ROS 2 and Foxglove protobuf.
#[test]
fn sample_writes_generated_scans_readable_by_independent_readers() {
    let dir = tempfile::tempdir().unwrap();
    for (format, scale) in [("ros2", 1usize), ("foxglove", 2)] {
        let out = dir.path().join(format!("sample_{format}.mcap"));
        let scale_arg = scale.to_string();
        let o = run(&[
            "sample",
            "--n",
            "3",
            "--seed",
            "5",
            "--format",
            format,
            "--scale",
            &scale_arg,
            out.to_str().unwrap(),
            "--json",
        ]);
        assert!(o.status.success(), "{}", stderr(&o));
        let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        assert_eq!(v["scans"], 3);
        assert_eq!(v["rows"], 64 * scale);
        assert_eq!(v["columns"], 512 * scale);
        let keep = v["keep_rate"].as_f64().unwrap();
        // KITTI keeps ~88 % of rays; a trained model must be in that region, not all or nothing
        assert!((0.5..0.999).contains(&keep), "keep rate {keep}");
        let topics = ["depth", "raydrop_prob", "raydrop_mask", "range", "points"];
        if let Some(node) = node() {
            let r = node_read(&node, &out);
            for t in topics {
                let topic = format!("/rangegan/sample/{t}");
                assert_eq!(r["topics"][&topic]["messages"], 3, "{topic}: {r}");
            }
            assert_eq!(r["decoded"], 15);
            if format == "ros2" {
                let img = &r["images"]["/rangegan/sample/raydrop_mask"];
                assert_eq!(img[0], 64);
                assert_eq!(img[2], "mono8");
                let fields = &r["clouds"]["/rangegan/sample/points"];
                assert_eq!(
                    fields,
                    &serde_json::json!(["x", "y", "z", "range", "raydrop_prob"])
                );
            }
        }
        if format == "ros2"
            && let Some(py) = python()
        {
            let r = python_read(&py, &out);
            assert_eq!(r["decoded"], 15, "{r}");
            assert_eq!(r["images"]["/rangegan/sample/depth"][2], "32FC1");
            assert_eq!(r["metadata"]["rangegan.sample"]["model"], "shipped", "{r}");
        }
    }
    // same seed, same scans
    let a = dir.path().join("a.mcap");
    let b = dir.path().join("b.mcap");
    for p in [&a, &b] {
        let o = run(&[
            "sample",
            "--n",
            "2",
            "--seed",
            "9",
            p.to_str().unwrap(),
            "--quiet",
        ]);
        assert!(o.status.success(), "{}", stderr(&o));
    }
    assert_eq!(std::fs::read(&a).unwrap(), std::fs::read(&b).unwrap());
    let bad = run(&[
        "sample",
        "--n",
        "0",
        dir.path().join("c.mcap").to_str().unwrap(),
    ]);
    assert!(!bad.status.success());
    assert!(stderr(&bad).contains("--n"), "{}", stderr(&bad));
}

/// `rangegan-mcap info IN --json | head -1`: a reader that stops early ends the process
/// quietly (as Unix tools do), not with a panic about a broken pipe.
#[test]
fn a_closed_stdout_ends_quietly() {
    let mut child = bin()
        .args(["info", "sample_logs/drive_realistic.mcap", "--json"])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("binary runs");
    drop(child.stdout.take()); // the reader goes away before anything is printed
    let out = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!err.contains("panicked"), "{err}");
    assert_ne!(out.status.code(), Some(101), "{err}");
}

/// A folder holding recordings of two sensors (a 64-beam and a 16-beam simulation) is not
/// squeezed onto one grid: `train` and `calibrate-raydrop` refuse, naming the recording and
/// both sensors.
#[test]
fn training_on_two_sensors_at_once_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    std::fs::create_dir_all(&data).unwrap();
    for (name, sensor) in [("a_hdl64e.mcap", "hdl64e"), ("b_vlp16.mcap", "vlp16")] {
        let path = data.join(name);
        let o = run(&[
            "simulate",
            "--sensor",
            sensor,
            "--columns",
            "256",
            "--scans",
            "2",
            path.to_str().unwrap(),
        ]);
        assert!(o.status.success(), "{}", stderr(&o));
    }
    let run_dir = dir.path().join("run");
    let o = run(&[
        "train",
        run_dir.to_str().unwrap(),
        "--data",
        data.to_str().unwrap(),
        "--total-images",
        "8",
    ]);
    assert!(!o.status.success());
    let err = stderr(&o);
    assert!(
        err.contains("b_vlp16.mcap") && err.contains("16-beam") && err.contains("64-beam"),
        "{err}"
    );
}
