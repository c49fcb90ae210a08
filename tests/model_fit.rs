//! What `convert` writes for sensors the decoding model does not cover, on real recordings:
//! the Ouster OS1-64 clouds of an indoor MCAP (+-16 deg, 0.6-15 m) and an indoor VLP-16 get
//! prior-free channels on their own grids (every beam, the measured returns kept, the
//! recording's own drop rates), with one line saying so, also when imported from folders of
//! PCD or nuScenes files; `--model` decodes them through the
//! KITTI model anyway, with the warning of how far they are from it; a KITTI recording is
//! decoded through the model on its own grid, and skips the model with `--prior-free`.
//! Skips when the real data folder is absent.

mod common;

use std::path::{Path, PathBuf};

use common::*;
use rangegan_mcap::io::roundtrip::float_images;
use rangegan_mcap::lidar::{kitti, pcd};

/// One image message: height, width, values.
type Image = (usize, usize, Vec<f32>);

/// The `32FC1` images of `topic` in `path`, in log-time order (ROS 1 or ROS 2).
fn images(path: &Path, topic: &str) -> Vec<Image> {
    let images = float_images(&std::fs::read(path).unwrap(), topic).unwrap();
    images
        .into_iter()
        .map(|i| (i.height, i.width, i.values))
        .collect()
}

fn real_root(test: &str) -> Option<PathBuf> {
    real_data(test)
        .or_else(|| Some(PathBuf::from("/work/shared/real_lidar")).filter(|p| p.is_dir()))
}

/// Converts `input` with `flags` (fast, few steps) and returns stderr and the output's path.
fn convert(input: &Path, dir: &Path, flags: &[&str]) -> (String, PathBuf) {
    let output = dir.join("out.mcap");
    let mut args = vec![
        "convert",
        input.to_str().unwrap(),
        output.to_str().unwrap(),
        "--force",
        "--decoder",
        "gan",
        "--w-steps",
        "1",
        "--tune-steps",
        "1",
        "--json",
    ];
    args.extend_from_slice(flags);
    let o = run(&args);
    assert!(o.status.success(), "{}", stderr(&o));
    (stderr(&o), output)
}

/// Checks the prior-free channels of `topic`: `depth` and `raydrop_prob` on the grid of
/// `range`, every measured return kept exactly, drop rates strictly between 0 and 1 that
/// put the scans' drops more likely than their returns (by 0.05 on average: the HDL-32E pair's
/// second scan, fitted on its first alone, 0.139 against 0.080).
fn check_prior_free(output: &Path, topic: &str) {
    let ch = |s: &str| images(output, &format!("{topic}/rangegan/{s}"));
    let (range, depth, drop) = (ch("range"), ch("depth"), ch("raydrop_prob"));
    assert!(!range.is_empty() && range.len() == depth.len() && range.len() == drop.len());
    assert!(ch("x_d").is_empty(), "no x_d without a prior");
    for ((r, d), p) in range.iter().zip(&depth).zip(&drop) {
        assert_eq!((r.0, r.1), (d.0, d.1), "depth on the sensor's grid");
        assert_eq!((r.0, r.1), (p.0, p.1), "raydrop_prob on the sensor's grid");
        let returns: Vec<usize> = (0..r.2.len()).filter(|&k| r.2[k] > 0.0).collect();
        assert!(
            returns.iter().all(|&k| d.2[k] == r.2[k]),
            "measured returns kept"
        );
        let filled = (0..r.2.len())
            .filter(|&k| r.2[k] == 0.0 && d.2[k] > 0.0)
            .count();
        assert!(filled > 0, "dropped rays next to returns are completed");
        assert!(p.2.iter().all(|&x| x > 0.0 && x < 1.0));
        let mean = |keep: bool| {
            let v: Vec<f32> = (0..r.2.len())
                .filter(|&k| (r.2[k] > 0.0) == keep)
                .map(|k| p.2[k])
                .collect();
            v.iter().sum::<f32>() / v.len().max(1) as f32
        };
        assert!(
            mean(false) > mean(true) + 0.05,
            "drops {} returns {}",
            mean(false),
            mean(true)
        );
    }
}

#[test]
fn sensors_the_model_does_not_cover_get_prior_free_channels_on_their_own_grid() {
    let Some(root) = real_root("sensors_the_model_does_not_cover_get_prior_free_channels") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    // The real OS1-64 recording (two organized 64 x 2048 clouds, indoors).
    let input = root.join("mcap/pointcloudset_test.mcap");
    let topic = "/os1_cloud_node/points";
    let (err, output) = convert(&input, dir.path(), &[]);
    assert!(
        err.contains(topic) && err.contains("no decoding model covers"),
        "{err}"
    );
    assert_eq!(
        err.matches("no decoding model covers").count(),
        1,
        "one line per topic: {err}"
    );
    check_prior_free(&output, topic);
    let range = images(&output, &format!("{topic}/rangegan/range"));
    assert_eq!(range[0].0, 64, "every beam of the OS1-64");
    // An indoor VLP-16 (an unorganized cloud with a ring field).
    let scan = pcd::read_pcd(&first_file(&root.join("nebula"), ".pcd")).unwrap();
    let vlp = dir.path().join("vlp16.mcap");
    write_scans(&vlp, &[scan]);
    let (err, output) = convert(&vlp, dir.path(), &[]);
    assert!(err.contains("no decoding model covers"), "{err}");
    check_prior_free(&output, "/points");
    // A row per beam that returned (15 of the 16 indoors), none invented.
    assert!((15..=16).contains(&images(&output, "/points/rangegan/depth")[0].0));
}

/// `--model` decodes an uncovered sensor through the model: `x_d` is written, the warning says
/// how far the sensor is from the model, and the rows outside the model's view have no
/// rendering (x_d 0, x_n 1) while `depth` still keeps every return there.
#[test]
fn a_named_model_decodes_every_topic_and_says_how_far_it_is() {
    let Some(root) = real_root("a_named_model_decodes_every_topic") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let input = root.join("mcap/pointcloudset_test.mcap");
    let topic = "/os1_cloud_node/points";
    let model = Path::new(env!("CARGO_MANIFEST_DIR")).join("models/dusty2");
    let (err, output) = convert(&input, dir.path(), &["--model", model.to_str().unwrap()]);
    assert!(err.contains("far from the decoding model's"), "{err}");
    let ch = |s: &str| images(&output, &format!("{topic}/rangegan/{s}"));
    let (range, depth, x_d) = (ch("range"), ch("depth"), ch("x_d"));
    assert_eq!(x_d.len(), range.len());
    let (h, w) = (range[0].0, range[0].1);
    assert_eq!((x_d[0].0, x_d[0].1), (h, w), "x_d on the sensor's grid");
    let r = &range[0].2;
    assert!(
        (0..r.len())
            .filter(|&k| r[k] > 0.0)
            .all(|k| depth[0].2[k] == r[k])
    );
    // The OS1-64 gen 1's top rows (+16.6 deg) lie far above the model's +2.6 deg.
    assert!(x_d[0].2[..w].iter().all(|&d| d == 0.0));
    assert!(x_d[0].2[(h - 1) * w..].iter().any(|&d| d > 0.0));
}

/// `--prior-free` gives prior-free channels also where the shipped model covers the sensor:
/// two KITTI scans get the completion of their own returns and the recording's drop rates, no
/// `x_d`, and no line about coverage.
#[test]
fn prior_free_skips_the_model_where_it_covers() {
    let Some(root) = real_root("prior_free_skips_the_model_where_it_covers") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let mut files: Vec<PathBuf> = std::fs::read_dir(root.join("kitti_raw_drive_a"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "bin"))
        .collect();
    files.sort();
    let scans: Vec<_> = files[..2]
        .iter()
        .map(|f| kitti::read_bin(f).unwrap())
        .collect();
    let input = dir.path().join("kitti.mcap");
    write_scans(&input, &scans);
    let (err, output) = convert(&input, dir.path(), &["--prior-free"]);
    assert!(!err.contains("no decoding model covers"), "{err}");
    check_prior_free(&output, "/points");
    let err = run(&[
        "convert",
        "a.mcap",
        "b.mcap",
        "--prior-free",
        "--model",
        "m",
    ]);
    assert!(!err.status.success() && stderr(&err).contains("--model"));
}

/// A full-resolution KITTI scan (about 2 000 columns) is decoded through the model and
/// written on its own grid: `depth`, `x_d` and `raydrop_prob` as wide as `range`, every return
/// kept; `--upsample 2` doubles that grid.
#[test]
fn full_resolution_kitti_is_decoded_on_its_own_columns() {
    let Some(root) = real_root("full_resolution_kitti_is_decoded_on_its_own_columns") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let scan = kitti::read_bin(&first_file(&root.join("semantickitti_ssv3"), ".bin")).unwrap();
    let input = dir.path().join("kitti.mcap");
    write_scans(&input, &[scan]);
    let (err, output) = convert(&input, dir.path(), &[]);
    assert!(!err.contains("no decoding model covers"), "{err}");
    let ch = |s: &str| images(&output, &format!("/points/rangegan/{s}"));
    let (range, depth, x_d, drop) = (ch("range"), ch("depth"), ch("x_d"), ch("raydrop_prob"));
    let (h, w) = (range[0].0, range[0].1);
    assert!(h == 64 && w > 1900, "{h} x {w}");
    for img in [&depth[0], &x_d[0], &drop[0]] {
        assert_eq!((img.0, img.1), (h, w));
    }
    let r = &range[0].2;
    assert!(
        (0..r.len())
            .filter(|&k| r[k] > 0.0)
            .all(|k| depth[0].2[k] == r[k])
    );
    let rendered = x_d[0].2.iter().filter(|&&d| d > 0.0).count();
    assert!(
        rendered as f64 > 0.95 * r.len() as f64,
        "x_d covers the HDL-64E's rows"
    );
    // `--upsample 2` doubles the scan's own grid, and `--channels` takes its name.
    let name = format!("depth_128x{}", 2 * w);
    let (_, output) = convert(
        &input,
        dir.path(),
        &["--upsample", "2", "--channels", &name],
    );
    let up = images(&output, &format!("/points/rangegan/{name}"));
    assert_eq!((up[0].0, up[0].1), (128, 2 * w));
    assert!(images(&output, "/points/rangegan/depth").is_empty());
}

/// Folders of PCD files (an HDL-32E-like pair) and of nuScenes `.pcd.bin` scans import and
/// convert on their own grids; a folder holding two kinds of scan is refused by name.
#[test]
fn pcd_and_nuscenes_folders_import_and_convert_on_their_own_grids() {
    let Some(root) = real_root("pcd_and_nuscenes_folders_import_and_convert") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    for (folder, scans, beams) in [
        ("other_sensors/fast_gicp_hdl32e", 2, 32),
        ("nuscenes", 1, 32),
    ] {
        let mcap = dir.path().join("imported.mcap");
        let o = run(&[
            "import",
            root.join(folder).to_str().unwrap(),
            mcap.to_str().unwrap(),
            "--force",
            "--json",
        ]);
        assert!(o.status.success(), "{folder}: {}", stderr(&o));
        let summary: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        assert_eq!(summary["scans"], scans, "{folder}");
        let (err, output) = convert(&mcap, dir.path(), &[]);
        assert!(err.contains("no decoding model covers"), "{folder}: {err}");
        check_prior_free(&output, "/velodyne_points");
        let depth = images(&output, "/velodyne_points/rangegan/depth");
        assert_eq!(depth[0].0, beams, "{folder}");
    }
    // Two kinds of scan in one folder.
    let mixed = dir.path().join("mixed");
    std::fs::create_dir(&mixed).unwrap();
    let pcd = first_file(&root.join("other_sensors/fast_gicp_hdl32e"), ".pcd");
    std::fs::copy(&pcd, mixed.join("a.pcd")).unwrap();
    let nus = first_file(&root.join("nuscenes"), ".pcd.bin");
    std::fs::copy(&nus, mixed.join("b.pcd.bin")).unwrap();
    let o = run(&[
        "import",
        mixed.to_str().unwrap(),
        dir.path().join("m.mcap").to_str().unwrap(),
    ]);
    assert_eq!(o.status.code(), Some(1));
    let err = stderr(&o);
    assert!(
        err.contains("more than one kind") && err.contains(".pcd.bin (nuScenes)"),
        "{err}"
    );
}
