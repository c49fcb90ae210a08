//! End-to-end `segment train | eval | picture` through the built binary: a network trained on
//! a simulated recording learns (road found on held-out simulated scans), a run stopped by
//! its time limit resumes from its checkpoint, scores on real labelled SemanticKITTI scans
//! (skipped without the real data), the comparison picture, validation that chooses the
//! exported network and stops a flat run, and clear errors for recordings without labels.

mod common;

use std::path::Path;

use common::{real_data, run, stderr};

fn simulate(path: &Path, scene: &str, scans: &str) {
    let out = run(&[
        "--quiet",
        "simulate",
        "--scene",
        scene,
        "--scans",
        scans,
        "--columns",
        "512",
        path.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
}

fn json(args: &[&str]) -> serde_json::Value {
    let out = run(args);
    assert!(out.status.success(), "{args:?}: {}", stderr(&out));
    serde_json::from_slice(&out.stdout).expect("JSON on stdout")
}

fn iou(report: &serde_json::Value, class: &str) -> f64 {
    report["classes"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["class"] == class)
        .and_then(|c| c["iou"].as_f64())
        .unwrap_or(0.0)
}

#[test]
fn trains_resumes_scores_and_draws() {
    let dir = tempfile::tempdir().unwrap();
    let train = dir.path().join("train.mcap");
    let heldout = dir.path().join("heldout.mcap");
    simulate(&train, "11", "8");
    simulate(&heldout, "12", "3");
    let run_dir = dir.path().join("run");
    let r = run_dir.to_str().unwrap();
    let t = train.to_str().unwrap();

    // A time limit stops after the first step with a checkpoint; the next call resumes.
    let first = json(&[
        "--json",
        "segment",
        "train",
        r,
        t,
        "--steps",
        "60",
        "--minutes",
        "0.0001",
    ]);
    assert_eq!(first["finished"], false);
    let stopped_at = first["steps"].as_u64().unwrap();
    assert!((1..60).contains(&stopped_at), "{first}");
    let second = json(&["--json", "segment", "train", r, t, "--steps", "60"]);
    assert_eq!(
        (second["steps"].as_u64(), second["finished"].as_bool()),
        (Some(60), Some(true))
    );
    let log = std::fs::read_to_string(run_dir.join("log.jsonl")).unwrap();
    let steps: Vec<u64> = log
        .lines()
        .map(|l| {
            serde_json::from_str::<serde_json::Value>(l).unwrap()["step"]
                .as_u64()
                .unwrap()
        })
        .collect();
    assert_eq!(
        steps,
        vec![20, 40, 60],
        "the resumed run continues the step count"
    );

    // It learned: road on scans of another scene.
    let model = run_dir.join("model");
    let m = model.to_str().unwrap();
    let report = json(&[
        "--json",
        "segment",
        "eval",
        "--model",
        m,
        heldout.to_str().unwrap(),
    ]);
    assert_eq!(report["scans"], 3);
    assert!(report["points"].as_u64().unwrap() > 10_000, "{report}");
    assert!(
        iou(&report, "road") > 0.5,
        "road IoU after 60 steps: {report}"
    );

    let png = dir.path().join("figure.png");
    let out = run(&[
        "segment",
        "picture",
        "--model",
        m,
        "--model",
        m,
        heldout.to_str().unwrap(),
        png.to_str().unwrap(),
        "--scan",
        "2",
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let bytes = std::fs::read(&png).unwrap();
    assert_eq!(&bytes[..8], b"\x89PNG\r\n\x1a\n");
    let out = run(&[
        "segment",
        "picture",
        "--model",
        m,
        heldout.to_str().unwrap(),
        png.to_str().unwrap(),
        "--scan",
        "3",
        "--force",
    ]);
    assert!(
        !out.status.success() && stderr(&out).contains("scan 3 does not exist"),
        "{}",
        stderr(&out)
    );
    // The picture never replaces an input, and replaces an earlier picture only when told.
    let recording_before = std::fs::read(&heldout).unwrap();
    for (target, force, expect) in [
        (&heldout, true, "inputs are never modified"),
        (&png, false, "pass --force"),
    ] {
        let mut args = vec!["segment", "picture", "--model", m];
        args.extend([heldout.to_str().unwrap(), target.to_str().unwrap()]);
        if force {
            args.push("--force");
        }
        let out = run(&args);
        assert!(
            !out.status.success() && stderr(&out).contains(expect),
            "{}",
            stderr(&out)
        );
    }
    assert_eq!(std::fs::read(&heldout).unwrap(), recording_before);

    // Real labelled scans, never seen: every class is scored and the numbers are rates.
    let Some(real) = real_data("trains_resumes_scores_and_draws (real part)") else {
        return;
    };
    let real_mcap = dir.path().join("mini00.mcap");
    let out = run(&[
        "--quiet",
        "import",
        real.join("semantickitti_mini/00").to_str().unwrap(),
        real_mcap.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let report = json(&[
        "--json",
        "segment",
        "eval",
        "--model",
        m,
        real_mcap.to_str().unwrap(),
    ]);
    assert_eq!(report["scans"], 10);
    let classes = report["classes"].as_array().unwrap();
    assert_eq!(classes.len(), 8);
    for c in classes {
        assert!(c["points"].as_u64().unwrap() > 0, "{c}");
        for key in ["precision", "recall", "iou"] {
            assert!(
                c[key].is_null() || (0.0..=1.0).contains(&c[key].as_f64().unwrap()),
                "{c}"
            );
        }
    }
    let miou = report["miou"].as_f64().unwrap();
    assert!((0.0..=1.0).contains(&miou));
    // The frontal view is about a quarter of each revolution's returns.
    let share = report["frontal"]["points"].as_f64().unwrap() / report["points"].as_f64().unwrap();
    assert!((0.15..0.35).contains(&share), "{share}");
}

/// With validation recordings a run scores them on a schedule, exports the network that
/// scored best there (not the last), and stops once validation has not improved for
/// `--patience` validations.
#[test]
fn validation_chooses_the_exported_network_and_stops_a_flat_run() {
    let dir = tempfile::tempdir().unwrap();
    let train = dir.path().join("train.mcap");
    let val = dir.path().join("val.mcap");
    simulate(&train, "13", "4");
    simulate(&val, "14", "2");
    let run_dir = dir.path().join("run");
    let (r, t, v) = (
        run_dir.to_str().unwrap(),
        train.to_str().unwrap(),
        val.to_str().unwrap(),
    );
    let train_args = [
        "--json",
        "segment",
        "train",
        r,
        t,
        "--val",
        v,
        "--steps",
        "400",
        "--batch-size",
        "2",
        "--val-every",
        "5",
        "--patience",
        "2",
    ];
    let early = json(&[&train_args[..], &["--minutes", "0.0001"]].concat());
    assert!(run_dir.join("model/segment.json").exists(), "{early}");
    assert_eq!(early["best"]["step"], early["steps"], "{early}");
    let summary = json(&train_args);
    let log = std::fs::read_to_string(run_dir.join("log.jsonl")).unwrap();
    // The first call, stopped by its time limit before step 5, validated on its way out.
    assert!(log.lines().next().unwrap().contains("validation"), "{log}");
    let validations: Vec<(u64, f64)> = log
        .lines()
        .filter_map(|l| {
            let v: serde_json::Value = serde_json::from_str(l).unwrap();
            let v = v.get("validation")?.clone();
            Some((v["step"].as_u64().unwrap(), v["miou"].as_f64().unwrap()))
        })
        .collect();
    assert!(validations.len() >= 3, "{log}");
    assert!(validations[1..].iter().all(|(step, _)| step % 5 == 0));
    let (best_step, best) = validations
        .iter()
        .copied()
        .fold((0, f64::MIN), |b, v| if v.1 > b.1 { v } else { b });
    assert_eq!(summary["best"]["step"], best_step, "{summary}");
    assert_eq!(summary["best"]["miou"].as_f64(), Some(best));
    let exported: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run_dir.join("model/segment.json")).unwrap())
            .unwrap();
    assert_eq!(exported["steps"], best_step);
    // Flat: two validations after the best, and not one more.
    assert_eq!(summary["flattened"], true, "{summary}");
    let last = validations.last().unwrap().0;
    assert_eq!(last, best_step + 10, "{log}");
    assert_eq!(summary["steps"], last);
}

#[test]
fn recordings_without_labels_are_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let unlabelled = dir.path().join("unlabelled.mcap");
    let out = run(&[
        "--quiet",
        "simulate",
        "--scans",
        "2",
        "--columns",
        "512",
        unlabelled.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    // A KITTI folder without labels/ imports fine but cannot train or score a network.
    let bins = dir.path().join("bins");
    std::fs::create_dir_all(&bins).unwrap();
    let points: Vec<u8> = (0..2000)
        .flat_map(|i| {
            let a = i as f32 * 0.01;
            [10.0 * a.cos(), 10.0 * a.sin(), -1.0 + 0.001 * i as f32, 0.5]
        })
        .flat_map(f32::to_le_bytes)
        .collect();
    std::fs::write(bins.join("000000.bin"), points).unwrap();
    let no_labels = dir.path().join("no_labels.mcap");
    let out = run(&[
        "--quiet",
        "import",
        bins.to_str().unwrap(),
        no_labels.to_str().unwrap(),
    ]);
    assert!(out.status.success(), "{}", stderr(&out));
    let run_dir = dir.path().join("run");
    let out = run(&[
        "segment",
        "train",
        run_dir.to_str().unwrap(),
        no_labels.to_str().unwrap(),
        "--steps",
        "2",
    ]);
    let err = stderr(&out);
    assert!(!out.status.success());
    assert!(
        err.contains("no_labels.mcap") && err.contains("label"),
        "{err}"
    );
    let out = run(&[
        "segment",
        "eval",
        "--model",
        dir.path().to_str().unwrap(),
        unlabelled.to_str().unwrap(),
    ]);
    assert!(
        !out.status.success() && stderr(&out).contains("not a segmentation model folder"),
        "{}",
        stderr(&out)
    );
}

/// A model folder whose `segment.json` asks for impossible or enormous layers gets an error
/// naming the file, before anything is built (no panic, no huge allocation).
#[test]
fn model_folders_with_bad_sizes_are_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let rec = dir.path().join("labelled.mcap");
    simulate(&rec, "3", "1");
    let shipped = Path::new(env!("CARGO_MANIFEST_DIR")).join("models/segment/A/s0");
    let text = std::fs::read_to_string(shipped.join("segment.json")).unwrap();
    for widths in ["[0, 0, 0, 0]", "[100000, 100000, 100000, 100000]", "[]"] {
        let model = dir.path().join("model");
        std::fs::create_dir_all(&model).unwrap();
        std::fs::copy(shipped.join("net.bpk"), model.join("net.bpk")).unwrap();
        let mut info: serde_json::Value = serde_json::from_str(&text).unwrap();
        info["net"]["widths"] = serde_json::from_str(widths).unwrap();
        std::fs::write(model.join("segment.json"), info.to_string()).unwrap();
        let out = run(&[
            "segment",
            "eval",
            "--model",
            model.to_str().unwrap(),
            rec.to_str().unwrap(),
        ]);
        assert_eq!(out.status.code(), Some(1), "{widths}: {}", stderr(&out));
        assert!(
            stderr(&out).contains("segment.json"),
            "{widths}: {}",
            stderr(&out)
        );
        assert!(
            stderr(&out).contains("widths"),
            "{widths}: {}",
            stderr(&out)
        );
    }
}

/// Real KITTI object scans with car and pedestrian boxes: `import` labels them partially,
/// a network trains on them beside fully labelled scans, and scoring counts only the points
/// that carry one class (car, person, or a cyclist's `other`).
#[test]
fn kitti_object_boxes_import_as_partial_labels_that_train_and_score() {
    let Some(real) = real_data("kitti_object_boxes_import_as_partial_labels_that_train_and_score")
    else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let acdc = real.join("kitti_object_acdc");
    let folder = dir.path().join("boxes");
    // Three frames, two with pedestrians (000010, 000011).
    for (sub, ext) in [("velodyne", "bin"), ("label_2", "txt"), ("calib", "txt")] {
        std::fs::create_dir_all(folder.join(sub)).unwrap();
        for frame in ["000009", "000010", "000011"] {
            let name = format!("{frame}.{ext}");
            std::fs::copy(acdc.join(sub).join(&name), folder.join(sub).join(&name)).unwrap();
        }
    }
    let boxes = dir.path().join("boxes.mcap");
    let imported = json(&[
        "--json",
        "import",
        folder.to_str().unwrap(),
        boxes.to_str().unwrap(),
    ]);
    assert_eq!(imported["scans"], 3);
    assert_eq!(imported["labelled"], 3);
    let run_dir = dir.path().join("run");
    let trained = json(&[
        "--json",
        "segment",
        "train",
        run_dir.to_str().unwrap(),
        boxes.to_str().unwrap(),
        "--steps",
        "3",
        "--batch-size",
        "2",
    ]);
    assert_eq!(trained["steps"], 3, "{trained}");
    let report = json(&[
        "--json",
        "segment",
        "eval",
        "--model",
        run_dir.join("model").to_str().unwrap(),
        boxes.to_str().unwrap(),
    ]);
    let points = |class: &str| {
        report["classes"]
            .as_array()
            .unwrap()
            .iter()
            .find(|c| c["class"] == class)
            .map(|c| c["points"].as_u64().unwrap())
            .unwrap()
    };
    assert!(points("car") > 100 && points("person") > 10, "{report}");
    for class in ["road", "sidewalk", "building", "vegetation", "pole"] {
        assert_eq!(points(class), 0, "{class}: boxes name only car and person");
    }
    // Scored points are the boxed ones: a small share of the returns.
    assert!(report["points"].as_u64().unwrap() < 10_000, "{report}");
}
