//! The scans measured on: held-out (or validation) KITTI scans projected onto 64 x 512
//! and, at full resolution, 64 x 2048; training scans for tuning.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use rangegan_mcap::lidar::{self, RangeImage, SensorProfile, Strategy};
use rangegan_mcap::model::data::{MAX_DEPTH_M, MIN_DEPTH_M, kitti_training_files};

/// One held-out scan: its 64 x 512 projection and, for full-resolution scans, 64 x 2048.
pub(crate) struct Scan {
    pub(crate) name: String,
    pub(crate) image: RangeImage,
    pub(crate) full: Option<RangeImage>,
}

pub(crate) fn valid_range(img: &mut RangeImage) {
    for r in &mut img.range_m {
        if !(MIN_DEPTH_M..=MAX_DEPTH_M).contains(r) {
            *r = 0.0;
        }
    }
}

/// Projects `path` onto 64 x 512 and, with `full`, 64 x 2048 (kept only when the scan is
/// full resolution: more than twice the 512-column returns).
pub(crate) fn load_scan(data: &Path, path: &Path, full: bool) -> Result<Scan> {
    let p512 = SensorProfile::kitti_hdl64e().with_columns(512);
    let p2048 = SensorProfile::kitti_hdl64e().with_columns(2048);
    let scan = lidar::kitti::read_bin(path)?;
    let mut image = lidar::project(&scan, &p512, Strategy::Auto)?;
    valid_range(&mut image);
    let full = if full {
        let mut f = lidar::project(&scan, &p2048, Strategy::Auto)?;
        valid_range(&mut f);
        (f.valid_count() > 2 * image.valid_count()).then_some(f)
    } else {
        None
    };
    let name = path
        .strip_prefix(data)
        .unwrap_or(path)
        .display()
        .to_string();
    Ok(Scan { name, image, full })
}

pub(crate) fn load_scans(data: &Path, validation: Option<&str>) -> Result<Vec<Scan>> {
    if let Some(dir) = validation {
        let (_, files) =
            rangegan_mcap::model::data::kitti_validation_split(data, &[dir.to_string()])?;
        return files
            .iter()
            .step_by(3)
            .map(|f| load_scan(data, f, true))
            .collect();
    }
    let mut out = Vec::new();
    for dir in ["semantickitti_ssv3", "patchworkpp"] {
        let mut files: Vec<PathBuf> = std::fs::read_dir(data.join(dir))
            .with_context(|| format!("failed to list {dir}"))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|e| e == "bin"))
            .collect();
        files.sort();
        for f in files {
            out.push(load_scan(data, &f, true)?);
        }
    }
    for f in rangegan_mcap::model::data::kitti_heldout_files(data)? {
        out.push(load_scan(data, &f, false)?);
    }
    Ok(out)
}

/// `n` training scans spread evenly over the training files (for tuning only).
pub(crate) fn load_training_scans(data: &Path, n: usize) -> Result<Vec<Scan>> {
    let files = kitti_training_files(data)?;
    let step = (files.len() / n.max(1)).max(1);
    files
        .iter()
        .step_by(step)
        .take(n)
        .map(|f| load_scan(data, f, true))
        .collect()
}
