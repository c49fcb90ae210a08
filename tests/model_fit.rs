//! The warning for a sensor far from the decoding model's, on a real recording: the Ouster
//! OS1-64 clouds of an indoor MCAP (+-16 deg, 0.6-15 m) decoded against the KITTI HDL-64E
//! model. Skips when the real data folder is absent.

mod common;

use std::path::PathBuf;

use common::*;

#[test]
fn an_indoor_ouster_recording_is_warned_about_and_still_converted() {
    // `../shared/real_lidar` beside the repository, else the shared checkout's copy.
    let Some(root) = real_data("an_indoor_ouster_recording_is_warned_about")
        .or_else(|| Some(PathBuf::from("/work/shared/real_lidar")).filter(|p| p.is_dir()))
    else {
        return;
    };
    let input = root.join("mcap/pointcloudset_test.mcap");
    let dir = tempfile::tempdir().unwrap();
    let output = dir.path().join("out.mcap");
    let o = run(&[
        "convert",
        input.to_str().unwrap(),
        output.to_str().unwrap(),
        "--channels",
        "range,depth",
        "--w-steps",
        "1",
        "--tune-steps",
        "1",
        "--json",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let err = stderr(&o);
    assert!(
        err.contains("/os1_cloud_node/points") && err.contains("far from the decoding model's"),
        "{err}"
    );
    let summary: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let fit = summary["report"]["model_fit"].as_array().unwrap();
    assert_eq!(fit.len(), 1, "one warning per topic, not per scan");
    let inside: f64 = fit[0]["message"]
        .as_str()
        .unwrap()
        .split("only ")
        .nth(1)
        .and_then(|t| t.split(' ').next())
        .and_then(|n| n.parse().ok())
        .unwrap();
    assert!(inside < 50.0, "{inside} % inside the model's view");
    // Both chosen channels are written for both scans.
    assert_eq!(summary["report"]["outputs_written"], 4);
    assert_eq!(summary["manifest"]["warnings"], 1);
}
