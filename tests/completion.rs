//! Completion of dropped rays as `convert` writes it in `depth`, on real KITTI scans that no
//! model trained on: holes of several kinds cut into them, the recording converted with the
//! default fill (the learned hole fill) and with `--upsample-method guided` (the completion
//! it corrects), and every cut pixel with a true return scored against the scan itself; on a
//! grid finer than the scans' returns and on every fourth beam, against interpolating the
//! scan's rows.
//! Skips with a message when `../shared/real_lidar` is absent.

mod common;
// The completion examples' holes and interpolation baselines; the tests use only some.
#[allow(dead_code)]
#[path = "../examples/common/holed.rs"]
mod holed;

use std::path::{Path, PathBuf};

use common::{bin, real_data, write_scans};

use rangegan_mcap::io::roundtrip;
use rangegan_mcap::lidar::holes::HoleKind;
use rangegan_mcap::lidar::{RangeImage, Scan, SensorProfile, Strategy, kitti, project};
use rangegan_mcap::util::rng::{Rng, key_hash};

const KINDS: [HoleKind; 3] = [HoleKind::Pixels, HoleKind::Large, HoleKind::Objects];

/// The six full-resolution held-out KITTI scans on the 64 x 512 grid.
fn held_out(root: &Path) -> Vec<RangeImage> {
    let profile = SensorProfile::kitti_hdl64e().with_columns(512);
    let mut bins: Vec<PathBuf> = ["semantickitti_ssv3", "patchworkpp"]
        .iter()
        .flat_map(|sub| std::fs::read_dir(root.join(sub)).unwrap())
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "bin"))
        .collect();
    bins.sort();
    assert_eq!(bins.len(), 6, "expected 3 + 3 KITTI scans");
    bins.iter()
        .map(|b| project(&kitti::read_bin(b).unwrap(), &profile, Strategy::Auto).unwrap())
        .collect()
}

/// The returns of `image` outside `mask`, with their beams.
fn degraded(image: &RangeImage, mask: &[bool]) -> Scan {
    let kept: Vec<usize> = (0..mask.len())
        .filter(|&k| image.range_m[k] > 0.0 && !mask[k])
        .collect();
    let mut scan = Scan::from_xyz(kept.iter().map(|&k| image.xyz[k]).collect());
    scan.ring = Some(kept.iter().map(|&k| (k / image.width) as u16).collect());
    scan
}

/// `depth` of each scan of `input` converted on `sensor` (a built-in name or a profile file)
/// at `columns` with `flags`.
fn depth(
    input: &Path,
    output: &Path,
    sensor: &str,
    columns: usize,
    flags: &[&str],
) -> Vec<Vec<f32>> {
    let columns = columns.to_string();
    let out = bin()
        .args(["--quiet", "convert"])
        .arg(input)
        .arg(output)
        .args(["--sensor", sensor, "--columns", &columns, "--force"])
        .args(flags)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let bytes = std::fs::read(output).unwrap();
    let images = roundtrip::float_images(&bytes, "/points/rangegan/depth").unwrap();
    images.into_iter().map(|i| i.values).collect()
}

#[test]
fn the_learned_hole_fill_beats_the_completion_it_corrects_on_every_kind_of_hole() {
    let Some(root) = real_data("the_learned_hole_fill_beats_the_completion_it_corrects") else {
        return;
    };
    let scans = held_out(&root);
    let masks: Vec<(HoleKind, Vec<bool>)> = (scans.iter().enumerate())
        .map(|(i, s)| {
            let kind = KINDS[i % KINDS.len()];
            let mut rng = Rng::new(key_hash(&[91, i as u64]));
            (kind, kind.cut(&s.range_m, s.height, s.width, &mut rng))
        })
        .collect();
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("holes.mcap");
    let recording: Vec<Scan> = (scans.iter().zip(&masks))
        .map(|(s, (_, m))| degraded(s, m))
        .collect();
    write_scans(&input, &recording);
    let output = dir.path().join("out.mcap");
    let learned = depth(&input, &output, "hdl64e", 512, &[]);
    let guided = depth(
        &input,
        &output,
        "hdl64e",
        512,
        &["--upsample-method", "guided"],
    );
    assert_eq!(learned.len(), 6);
    for kind in KINDS {
        let (mut n, mut sums) = (0usize, [0.0f64; 2]);
        for (s, (k_, mask)) in masks.iter().enumerate() {
            if *k_ != kind {
                continue;
            }
            let truth = &scans[s].range_m;
            for k in (0..mask.len()).filter(|&k| mask[k] && truth[k] > 0.0) {
                n += 1;
                sums[0] += f64::from((learned[s][k] - truth[k]).abs());
                sums[1] += f64::from((guided[s][k] - truth[k]).abs());
            }
            // Measured returns are kept as measured.
            for k in (0..mask.len()).filter(|&k| !mask[k] && truth[k] > 0.0) {
                assert_eq!(
                    learned[s][k],
                    guided[s][k],
                    "{} scan {s} pixel {k}",
                    kind.name()
                );
            }
        }
        let [l, g] = sums.map(|v| v / n as f64);
        eprintln!(
            "{}: {n} pixels, MAE learned {l:.3} m, guided {g:.3} m",
            kind.name()
        );
        assert!(n > 1000, "{}: {n} pixels", kind.name());
        assert!(l < 0.97 * g, "{}: learned {l} m against {g} m", kind.name());
    }
}

/// Mean absolute error of `depth` on the cut pixels of each scan with a true return.
fn cut_mae(depth: &[Vec<f32>], scans: &[RangeImage], masks: &[Vec<bool>]) -> f64 {
    let (mut n, mut sum) = (0usize, 0.0f64);
    for ((d, s), mask) in depth.iter().zip(scans).zip(masks) {
        for k in (0..mask.len()).filter(|&k| mask[k] && s.range_m[k] > 0.0) {
            n += 1;
            sum += f64::from((d[k] - s.range_m[k]).abs());
        }
    }
    assert!(n > 1000, "{n} cut pixels");
    sum / n as f64
}

/// Three scans of a drive no model trained on, on KITTI's grid at `columns`.
fn validation_scans(root: &Path, columns: usize) -> Vec<RangeImage> {
    let profile = SensorProfile::kitti_hdl64e().with_columns(columns);
    ["0000000000.bin", "0000000030.bin", "0000000060.bin"]
        .iter()
        .map(|f| root.join("kitti_raw_drive_d").join(f))
        .map(|b| project(&kitti::read_bin(&b).unwrap(), &profile, Strategy::Auto).unwrap())
        .collect()
}

/// `kind` of hole cut into each of `scans`, converted on `sensor` at `columns`: MAE of
/// `depth`, and of interpolating each degraded scan along its rows, on the cut pixels.
fn depth_and_rows(
    scans: &[RangeImage],
    kind: HoleKind,
    sensor: &str,
    columns: usize,
) -> (f64, f64) {
    let masks: Vec<Vec<bool>> = (scans.iter().enumerate())
        .map(|(i, s)| {
            let mut rng = Rng::new(key_hash(&[93, i as u64]));
            kind.cut(&s.range_m, s.height, s.width, &mut rng)
        })
        .collect();
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("holes.mcap");
    let recording: Vec<Scan> = (scans.iter().zip(&masks))
        .map(|(s, m)| degraded(s, m))
        .collect();
    write_scans(&input, &recording);
    let output = dir.path().join("out.mcap");
    let depth = cut_mae(&depth(&input, &output, sensor, columns, &[]), scans, &masks);
    let rows: Vec<Vec<f32>> = (scans.iter().zip(&masks))
        .map(|(s, m)| holed::interpolate(&holed::observed(s, m), s.height, s.width, true))
        .collect();
    (depth, cut_mae(&rows, scans, &masks))
}

#[test]
fn a_grid_finer_than_the_returns_gets_depth_better_than_interpolating_its_rows() {
    let Some(root) = real_data("a_grid_finer_than_the_returns_gets_depth_better") else {
        return;
    };
    // Scans of a drive no model trained on hold about 30 000 points: on 1 024 columns nine
    // returns in ten have an empty ray beside them along the row.
    let scans = validation_scans(&root, 1024);
    let (default, rows) = depth_and_rows(&scans, HoleKind::Pixels, "hdl64e", 1024);
    eprintln!("single dropped rays at 1 024 columns: default {default:.3} m, rows {rows:.3} m");
    assert!(
        default < 0.9 * rows,
        "default {default} m against rows {rows} m"
    );
}

#[test]
fn every_fourth_beam_gets_depth_better_than_interpolating_its_rows() {
    let Some(root) = real_data("every_fourth_beam_gets_depth_better") else {
        return;
    };
    // The model covers KITTI's HDL-64E; with every fourth beam kept, its beams are four
    // times as far apart as those the decoded hole fill was fitted on.
    let scans: Vec<RangeImage> = (validation_scans(&root, 512).iter())
        .map(|s| holed::every_nth_row(s, 4))
        .collect();
    let mut profile = SensorProfile::kitti_hdl64e().with_columns(512);
    profile.elevation_deg = profile.elevation_deg.into_iter().step_by(4).collect();
    let dir = tempfile::tempdir().unwrap();
    let sensor = dir.path().join("every_fourth_beam.json");
    std::fs::write(&sensor, serde_json::to_string(&profile).unwrap()).unwrap();
    let (default, rows) = depth_and_rows(&scans, HoleKind::Small, sensor.to_str().unwrap(), 512);
    eprintln!("small holes on 16 of 64 beams: default {default:.3} m, rows {rows:.3} m");
    assert!(
        default < 0.95 * rows,
        "default {default} m against rows {rows} m"
    );
}
