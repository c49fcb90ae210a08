//! A prior for a sensor the shipped model does not cover, trained from the user's own MCAP
//! recordings: the real HDL-32E pair, one scan per recording. `train` reads the folder of
//! recordings with one held out, and its model records the sensor; `convert --model` then
//! decodes that sensor's scans as covered, on its grid; `calibrate-raydrop` fits and scores
//! x_n on the same recordings, `train-encoder` reads the model's grid, and simulator
//! pretraining ray-casts the sensor's own beams. Tiny runs: this checks the plumbing, not the
//! quality of a prior. Skips when the real data folder is absent.

mod common;

use std::path::{Path, PathBuf};

use common::*;
use rangegan_mcap::lidar::pcd;

fn real_root(test: &str) -> Option<PathBuf> {
    real_data(test)
        .or_else(|| Some(PathBuf::from("/work/shared/real_lidar")).filter(|p| p.is_dir()))
}

fn ok(args: &[&str]) -> std::process::Output {
    let o = run(args);
    assert!(o.status.success(), "{args:?}: {}", stderr(&o));
    o
}

/// `convert INPUT OUTPUT --force --model MODEL` with a one-step decode.
fn convert_with(model: &str, input: &Path, output: &Path) -> std::process::Output {
    ok(&[
        "convert",
        input.to_str().unwrap(),
        output.to_str().unwrap(),
        "--force",
        "--decoder",
        "gan",
        "--model",
        model,
        "--w-steps",
        "1",
        "--tune-steps",
        "1",
    ])
}

fn json(path: &Path) -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap()
}

/// The `sensor` a run's or model's config records: (name, beams, columns, min range).
fn sensor(config: &Path) -> (String, usize, usize, f64) {
    let s = &json(config)["sensor"];
    (
        s["name"].as_str().unwrap().to_string(),
        s["elevation_deg"].as_array().unwrap().len(),
        s["columns"].as_u64().unwrap() as usize,
        s["min_range_m"].as_f64().unwrap(),
    )
}

#[test]
fn a_prior_trained_on_a_sensors_recordings_covers_that_sensor() {
    let Some(root) = real_root("a_prior_trained_on_a_sensors_recordings_covers_that_sensor") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let recordings = dir.path().join("recordings");
    std::fs::create_dir(&recordings).unwrap();
    let pair = root.join("other_sensors/fast_gicp_hdl32e");
    let mut pcds: Vec<PathBuf> = std::fs::read_dir(&pair)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "pcd"))
        .collect();
    pcds.sort();
    assert_eq!(pcds.len(), 2);
    for (name, file) in ["drive_a", "drive_b"].iter().zip(&pcds) {
        write_scans(
            &recordings.join(format!("{name}.mcap")),
            &[pcd::read_pcd(file).unwrap()],
        );
    }
    let (rec, run_dir) = (recordings.to_str().unwrap(), dir.path().join("run"));
    let run_s = run_dir.to_str().unwrap();
    let o = ok(&[
        "--quiet",
        "train",
        run_s,
        "--data",
        rec,
        "--validation-recording",
        "drive_b",
        "--columns",
        "256",
        "--batch",
        "1",
        "--total-images",
        "2",
    ]);
    drop(o);
    let (name, beams, columns, _) = sensor(&run_dir.join("config.json"));
    assert_eq!((beams, columns), (32, 256), "{name}");
    assert!(run_dir.join("checkpoint/g_ema.bpk").is_file());
    // Rerun with a larger budget: it resumes from the checkpoint, on the cached dataset.
    let images = |run: &Path| json(&run.join("checkpoint/state.json"))["images"].clone();
    assert_eq!(images(&run_dir), 2);
    ok(&["--quiet", "train", run_s, "--total-images", "4"]);
    assert_eq!(images(&run_dir), 4);

    // The trained model covers its sensor: no warning, every channel on the sensor's grid.
    let output = dir.path().join("out.mcap");
    let input = recordings.join("drive_a.mcap");
    let o = convert_with(run_s, &input, &output);
    let err = stderr(&o);
    assert!(
        !err.contains("far from the decoding model") && !err.contains("no decoding model covers"),
        "{err}"
    );
    assert!(err.contains("has no ray-drop calibration"), "{err}");
    let bytes = std::fs::read(&output).unwrap();
    let image = |ch: &str| {
        rangegan_mcap::io::roundtrip::float_images(&bytes, &format!("/points/rangegan/{ch}"))
            .unwrap()
            .remove(0)
    };
    let (range, x_d) = (image("range"), image("x_d"));
    assert_eq!(range.height, 32);
    assert_eq!((x_d.height, x_d.width), (range.height, range.width));
    let rendered = x_d.values.iter().filter(|&&d| d > 0.0).count();
    assert!(
        rendered as f64 > 0.95 * x_d.values.len() as f64,
        "x_d on every beam of the sensor the model knows: {rendered} of {}",
        x_d.values.len()
    );

    // The calibration is fitted on the training recording and scored on the held-out one.
    let calibration = dir.path().join("calibration.json");
    let o = ok(&[
        "--json",
        "calibrate-raydrop",
        "--data",
        rec,
        "--validation-recording",
        "drive_b.mcap",
        "--model",
        run_s,
        "--scans",
        "4",
        "--out",
        calibration.to_str().unwrap(),
    ]);
    let summary: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(summary["scans"], 1, "{summary}");
    assert_eq!(summary["validation"]["scans"], 1, "{summary}");
    assert!(summary["validation"]["nll_calibrated"].as_f64().unwrap() > 0.0);
    let fitted = json(&calibration);
    assert_eq!(fitted["beams"].as_array().unwrap().len(), 32, "{fitted}");
    assert!(
        fitted["fitted_on"]
            .as_str()
            .unwrap()
            .contains("1 recordings"),
        "{fitted}"
    );
    // Beside the weights, the calibration is used, and nothing is said about its absence.
    std::fs::copy(&calibration, run_dir.join("calibration.json")).unwrap();
    let o = convert_with(run_s, &input, &output);
    assert!(
        !stderr(&o).contains("no ray-drop calibration"),
        "{}",
        stderr(&o)
    );

    // An encoder for the model reads the model's grid.
    let encoder = dir.path().join("encoder");
    ok(&[
        "train-encoder",
        encoder.to_str().unwrap(),
        "--data",
        rec,
        "--model",
        run_s,
        "--total-steps",
        "1",
    ]);
    let enc = json(&encoder.join("config.json"));
    assert_eq!(enc["encoder"]["height"], 32, "{enc}");
    assert_eq!(enc["encoder"]["width"], 256, "{enc}");
    let o = run(&[
        "train-encoder",
        dir.path().join("encoder2").to_str().unwrap(),
        "--data",
        rec,
        "--model",
        run_s,
        "--columns",
        "512",
    ]);
    assert_eq!(o.status.code(), Some(1));
    assert!(
        stderr(&o).contains("not the generator's 256 columns"),
        "{}",
        stderr(&o)
    );

    // Simulator pretraining ray-casts the sensor's own beams, in its own range.
    let sim = dir.path().join("sim");
    ok(&[
        "--quiet",
        "train",
        sim.to_str().unwrap(),
        "--sim-scans",
        "2",
        "--sensor",
        "os1-32",
        "--columns",
        "128",
        "--batch",
        "1",
        "--total-images",
        "1",
    ]);
    let (name, beams, columns, min_range) = sensor(&sim.join("config.json"));
    assert_eq!((name.as_str(), beams, columns), ("os1-32", 32, 128));
    assert!(
        min_range < 1.0,
        "an Ouster measures from 0.3 m: {min_range}"
    );
}

/// The real OS-1-128 PCAP capture goes end to end: imported, trained on (at 256 columns),
/// and its model decodes the capture's rotations on the unit's 128 beams.
#[test]
fn an_ouster_capture_trains_a_prior_of_its_128_beams() {
    let Some(root) = real_root("an_ouster_capture_trains_a_prior_of_its_128_beams") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let capture =
        root.join("other_sensors/ouster_os1_128_lb_3frames/OS-1-128_v2.3.0_1024x10_lb_n3.pcap");
    let mcap = dir.path().join("os128.mcap");
    ok(&[
        "--quiet",
        "import",
        capture.to_str().unwrap(),
        mcap.to_str().unwrap(),
    ]);
    let run_dir = dir.path().join("run");
    let (run_s, mcap_s) = (run_dir.to_str().unwrap(), mcap.to_str().unwrap());
    ok(&[
        "--quiet",
        "train",
        run_s,
        "--data",
        mcap_s,
        "--columns",
        "256",
        "--batch",
        "1",
        "--total-images",
        "2",
    ]);
    let (_, beams, columns, min_range) = sensor(&run_dir.join("config.json"));
    assert_eq!((beams, columns), (128, 256));
    assert!(
        min_range < 1.5,
        "the capture's nearest returns set the units: {min_range}"
    );
    let output = dir.path().join("out.mcap");
    let o = convert_with(run_s, &mcap, &output);
    assert!(
        !stderr(&o).contains("far from the decoding model"),
        "{}",
        stderr(&o)
    );
    let bytes = std::fs::read(&output).unwrap();
    let x_d = rangegan_mcap::io::roundtrip::float_images(&bytes, "/velodyne_points/rangegan/x_d")
        .unwrap();
    assert_eq!(x_d.len(), 3);
    assert!(x_d.iter().all(|i| (i.height, i.width) == (128, 1024)));
}

/// A sensor whose beams the networks cannot halve to their coarsest level is refused before
/// anything trains, with the reason; so is a folder of recordings of nothing.
#[test]
fn grids_the_networks_cannot_train_on_are_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let run_dir = dir.path().join("run");
    let o = run(&[
        "train",
        run_dir.to_str().unwrap(),
        "--sim-scans",
        "1",
        "--sensor",
        "hdl64e",
        "--columns",
        "100",
        "--batch",
        "1",
    ]);
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert!(stderr(&o).contains("must divide by 16"), "{}", stderr(&o));
    assert!(!run_dir.join("checkpoint").exists());
    let empty = dir.path().join("empty");
    std::fs::create_dir(&empty).unwrap();
    let o = run(&[
        "train",
        dir.path().join("run2").to_str().unwrap(),
        "--data",
        empty.to_str().unwrap(),
    ]);
    assert_eq!(o.status.code(), Some(1));
    assert!(stderr(&o).contains("no MCAP recordings"), "{}", stderr(&o));
}
