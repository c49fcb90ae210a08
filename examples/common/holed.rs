//! What the completion examples share: scans with holes cut into them, written as an MCAP
//! recording, converted by the built binary, and the channels read back.

use rangegan_mcap::model::spatial::prior;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use rangegan_mcap::io::roundtrip;
use rangegan_mcap::lidar::{self, RangeImage, Scan, SensorProfile, Strategy};

pub const TOPIC: &str = "/velodyne_points";

/// KITTI scans projected onto the HDL-64E grid at `columns` (every range kept).
pub fn project_all(files: &[PathBuf], columns: usize) -> Result<Vec<RangeImage>> {
    let profile = SensorProfile::kitti_hdl64e().with_columns(columns);
    files
        .iter()
        .map(|f| {
            let scan = lidar::kitti::read_bin(f)?;
            Ok(lidar::project(&scan, &profile, Strategy::Auto)?)
        })
        .collect()
}

/// Every `step`-th row of `image`: the scan of a sensor with fewer beams.
#[allow(dead_code)]
pub fn every_nth_row(image: &RangeImage, step: usize) -> RangeImage {
    fn rows<T: Copy>(v: &[T], w: usize, step: usize) -> Vec<T> {
        v.chunks(w).step_by(step).flatten().copied().collect()
    }
    let w = image.width;
    let mut angles = image.angles.clone();
    angles.height = image.height.div_ceil(step);
    angles.elevation_rad = rows(&image.angles.elevation_rad, w, step);
    angles.azimuth_rad = rows(&image.angles.azimuth_rad, w, step);
    RangeImage {
        height: angles.height,
        width: w,
        range_m: rows(&image.range_m, w, step),
        xyz: rows(&image.xyz, w, step),
        intensity: rows(&image.intensity, w, step),
        label: rows(&image.label, w, step),
        point_index: rows(&image.point_index, w, step),
        angles,
    }
}

/// The returns of `image` outside `mask`, as a scan whose ring field is the row.
pub fn degraded_scan(image: &RangeImage, mask: &[bool]) -> Scan {
    let kept: Vec<usize> = (0..image.range_m.len())
        .filter(|&k| image.range_m[k] > 0.0 && !mask[k])
        .collect();
    let mut scan = Scan::from_xyz(kept.iter().map(|&k| image.xyz[k]).collect());
    scan.ring = Some(kept.iter().map(|&k| (k / image.width) as u16).collect());
    scan.intensity = Some(kept.iter().map(|&k| image.intensity[k]).collect());
    scan
}

/// `image`'s ranges with the pixels of `mask` dropped.
pub fn observed(image: &RangeImage, mask: &[bool]) -> Vec<f32> {
    (0..image.range_m.len())
        .map(|k| if mask[k] { 0.0 } else { image.range_m[k] })
        .collect()
}

/// The release binary beside this example, or `bin`.
pub fn binary(bin: Option<PathBuf>) -> Result<PathBuf> {
    if let Some(b) = bin {
        return Ok(b);
    }
    let exe = std::env::current_exe()?;
    exe.parent()
        .and_then(Path::parent)
        .map(|d| d.join("rangegan-mcap"))
        .filter(|p| p.exists())
        .context("build the binary first: cargo build --release")
}

/// The `convert` flags that put KITTI scans on the HDL-64E grid at `columns`.
pub fn kitti_grid(columns: usize) -> Vec<String> {
    ["--sensor", "hdl64e", "--columns", &columns.to_string()]
        .map(String::from)
        .to_vec()
}

/// The images of each channel of `suffixes` that `bin convert FLAGS` writes for `scans`
/// (one recording, in order, on the grid that the flags `grid` name). A channel that
/// `convert` does not write (x_d where no model covers the sensor) comes back empty.
pub fn convert(
    grid: &[String],
    bin: &Path,
    dir: &Path,
    scans: &[Scan],
    flags: &[String],
    suffixes: &[&str],
) -> Result<Vec<Vec<Vec<f32>>>> {
    let (input, output) = (dir.join("in.mcap"), dir.join("out.mcap"));
    roundtrip::write_scans(&input, TOPIC, "velodyne", scans)?;
    let status = std::process::Command::new(bin)
        .args(["--quiet", "convert"])
        .arg(&input)
        .arg(&output)
        .arg("--force")
        .args(grid)
        .args(flags)
        .status()?;
    if !status.success() {
        bail!("convert {} failed", flags.join(" "));
    }
    let bytes = std::fs::read(&output)?;
    suffixes
        .iter()
        .map(|suffix| {
            let topic = format!("{TOPIC}/rangegan/{suffix}");
            let images = roundtrip::float_images(&bytes, &topic)?;
            Ok(images.into_iter().map(|i| i.values).collect())
        })
        .collect()
}

/// Each missing pixel of `observed` (0 = none) on a line between the nearest returns before
/// and after it along rows (`along_rows`, circular) or along columns; the one neighbour
/// where there is only one; 0 where the line holds no return. The model's own
/// interpolation prior ([`prior::interpolate`]), without its reach.
#[allow(dead_code)] // not every example scores interpolation
pub fn interpolate(observed: &[f32], h: usize, w: usize, along_rows: bool) -> Vec<f32> {
    prior::interpolate(observed, (h, w), along_rows, along_rows, |_, _, _| 0.0)
        .into_iter()
        .map(|line| line.map_or(0.0, |(r, _)| r))
        .collect()
}
