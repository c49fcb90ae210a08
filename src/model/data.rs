//! Training data for the GAN: KITTI scans projected once to 64 x 512 inverse-depth images
//! (network units, no return = -1) and cached in one binary file, so training never
//! re-projects. Owns the train/held-out split of `real_lidar/` and the cache format.

use std::fs::File;
use std::io::{BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};

use crate::lidar::{self, AngleGrid, SensorProfile, Strategy};

/// Smallest valid depth; also the scale of the inverse depth x_d = MIN_DEPTH_M / depth.
pub const MIN_DEPTH_M: f32 = 1.45;
/// Largest valid depth.
pub const MAX_DEPTH_M: f32 = 80.0;

/// In network units, a pixel at or below this is a dropped ray (-1), anything above a return.
pub const DROPPED: f32 = -1.0 + 1e-4;

/// Range image (meters, 0 = no return) -> network units: 2 * 1.45 / depth - 1 for depths in
/// [1.45, 80] m, -1 elsewhere.
pub fn range_to_network(range_m: &[f32]) -> Vec<f32> {
    range_m
        .iter()
        .map(|&d| {
            if (MIN_DEPTH_M..=MAX_DEPTH_M).contains(&d) {
                2.0 * MIN_DEPTH_M / d - 1.0
            } else {
                -1.0
            }
        })
        .collect()
}

/// Network units -> depth in meters (0 = no return).
pub fn network_to_range(x: &[f32]) -> Vec<f32> {
    x.iter()
        .map(|&v| {
            let x_d = (v + 1.0) * 0.5;
            if x_d > MIN_DEPTH_M / MAX_DEPTH_M * 0.5 {
                MIN_DEPTH_M / x_d
            } else {
                0.0
            }
        })
        .collect()
}

/// The training scans of `real_lidar/`: every KITTI raw drive (`kitti_raw_*/*.bin`), the
/// KITTI object and odometry folders (`kitti_object_*/velodyne/*.bin`,
/// `kitti_odometry_*/velodyne/*.bin`) and `semantickitti_mini/SS/velodyne/*.bin` for every
/// SS except 00 and 07. Those two sequences,
/// `semantickitti_ssv3` and `patchworkpp` are the evaluation data and never trained on.
pub fn kitti_training_files(real_lidar: &Path) -> Result<Vec<PathBuf>> {
    let mut files = Vec::new();
    for drive in subdirs(real_lidar)? {
        let name = dir_name(&drive);
        if name.starts_with(KITTI_RAW_PREFIX) {
            files.extend(bins_in(&drive)?);
        } else if KITTI_VELODYNE_PREFIXES.iter().any(|p| name.starts_with(p))
            && drive.join("velodyne").is_dir()
        {
            files.extend(bins_in(&drive.join("velodyne"))?);
        }
    }
    for seq in subdirs(&real_lidar.join("semantickitti_mini"))? {
        if !HELD_OUT_SEQUENCES.contains(&dir_name(&seq)) {
            files.extend(bins_in(&seq.join("velodyne"))?);
        }
    }
    if files.is_empty() {
        bail!(
            "no training scans in '{}' (expected {KITTI_RAW_PREFIX}*/ or semantickitti_mini/)",
            real_lidar.display()
        );
    }
    Ok(files)
}

/// A validation split for choosing between trained models: the training scans without the
/// named KITTI raw drives, and those drives' scans. A drive is a place, so its scans are
/// unlike every other training scan, where held-out frames of a trained-on sequence are not.
pub fn kitti_validation_split(
    real_lidar: &Path,
    drives: &[String],
) -> Result<(Vec<PathBuf>, Vec<PathBuf>)> {
    let mut validation = Vec::new();
    for drive in drives {
        if !drive.starts_with(KITTI_RAW_PREFIX) || drive.contains(['/', '\\']) {
            bail!("validation drive '{drive}' is not a {KITTI_RAW_PREFIX}* folder name");
        }
        let scans = bins_in(&real_lidar.join(drive))?;
        if scans.is_empty() {
            bail!(
                "validation drive '{drive}' in '{}' has no .bin scans",
                real_lidar.display()
            );
        }
        validation.extend(scans);
    }
    let training: Vec<PathBuf> = kitti_training_files(real_lidar)?
        .into_iter()
        .filter(|f| !validation.contains(f))
        .collect();
    if training.is_empty() {
        bail!(
            "no training scans left in '{}' after setting aside {drives:?}",
            real_lidar.display()
        );
    }
    Ok((training, validation))
}

/// Folders of KITTI raw drives (training data) start with this.
pub const KITTI_RAW_PREFIX: &str = "kitti_raw_";

/// Folders of KITTI object and odometry scans (training data, in `velodyne/`) start with these.
pub const KITTI_VELODYNE_PREFIXES: [&str; 2] = ["kitti_object_", "kitti_odometry_"];

/// SemanticKITTI sequences kept out of training.
pub const HELD_OUT_SEQUENCES: [&str; 2] = ["00", "07"];

/// Folders of `real_lidar/` that are evaluation data only, besides the held-out sequences.
pub const EVALUATION_FOLDERS: [&str; 2] = ["semantickitti_ssv3", "patchworkpp"];

/// The held-out evaluation scans (sequences 00 and 07 of `semantickitti_mini`).
pub fn kitti_heldout_files(real_lidar: &Path) -> Result<Vec<PathBuf>> {
    let mut files = Vec::new();
    for seq in HELD_OUT_SEQUENCES {
        files.extend(bins_in(
            &real_lidar
                .join("semantickitti_mini")
                .join(seq)
                .join("velodyne"),
        )?);
    }
    Ok(files)
}

fn dir_name(p: &Path) -> &str {
    p.file_name().and_then(|n| n.to_str()).unwrap_or("")
}

/// Sub-folders of `dir`, sorted.
fn subdirs(dir: &Path) -> Result<Vec<PathBuf>> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("failed to list '{}'", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_dir())
        .collect();
    v.sort();
    Ok(v)
}

fn bins_in(dir: &Path) -> Result<Vec<PathBuf>> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("failed to list '{}'", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "bin"))
        .collect();
    v.sort();
    Ok(v)
}

/// Images in network units, `[n, H, W]` row-major, on one shared angle grid.
#[derive(Debug, Clone, PartialEq)]
pub struct RangeDataset {
    pub height: usize,
    pub width: usize,
    pub images: Vec<f32>,
    pub angles: AngleGrid,
}

impl RangeDataset {
    pub fn len(&self) -> usize {
        self.images.len() / (self.height * self.width).max(1)
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    pub fn image(&self, i: usize) -> &[f32] {
        let n = self.height * self.width;
        &self.images[i * n..(i + 1) * n]
    }

    /// Project KITTI `.bin` scans with the HDL-64E profile at `width` columns (in parallel,
    /// in file order). A scan that cannot be read or projected fails the whole build, naming
    /// the file.
    pub fn from_kitti_files(files: &[PathBuf], width: usize) -> Result<Self> {
        use rayon::prelude::*;
        let profile = SensorProfile::kitti_hdl64e().with_columns(width);
        let angles = profile.angle_grid();
        let (height, width) = (angles.height, angles.width);
        let per_file: Vec<Vec<f32>> = files
            .par_iter()
            .map(|path| -> Result<Vec<f32>> {
                let scan = lidar::kitti::read_bin(path)
                    .with_context(|| format!("failed to read '{}'", path.display()))?;
                let image = lidar::project(&scan, &profile, Strategy::Auto)
                    .with_context(|| format!("failed to project '{}'", path.display()))?;
                if image.height != height || image.width != width {
                    bail!(
                        "'{}' projected to {}x{}",
                        path.display(),
                        image.height,
                        image.width
                    );
                }
                Ok(range_to_network(&image.range_m))
            })
            .collect::<Result<_>>()?;
        Ok(Self::from_images(angles, per_file.concat()))
    }

    /// A dataset from images in network units on `angles`' grid, `[n, H, W]` row-major.
    pub fn from_images(angles: AngleGrid, images: Vec<f32>) -> Self {
        debug_assert_eq!(images.len() % angles.len().max(1), 0);
        Self {
            height: angles.height,
            width: angles.width,
            images,
            angles,
        }
    }

    const MAGIC: &'static [u8; 8] = b"RGDSv001";

    /// Write the cache: magic, n, H, W (u64 LE), elevation, azimuth, images (f32 LE).
    pub fn save(&self, path: &Path) -> Result<()> {
        let tmp = path.with_extension("tmp");
        {
            let f = File::create(&tmp)
                .with_context(|| format!("failed to create '{}'", tmp.display()))?;
            let mut w = BufWriter::new(f);
            w.write_all(Self::MAGIC)?;
            for v in [self.len(), self.height, self.width] {
                w.write_all(&(v as u64).to_le_bytes())?;
            }
            for v in self
                .angles
                .elevation_rad
                .iter()
                .chain(&self.angles.azimuth_rad)
                .chain(&self.images)
            {
                w.write_all(&v.to_le_bytes())?;
            }
            w.flush()?;
        }
        std::fs::rename(&tmp, path)
            .with_context(|| format!("failed to rename '{}'", tmp.display()))?;
        Ok(())
    }

    pub fn load(path: &Path) -> Result<Self> {
        let f = File::open(path).with_context(|| format!("failed to open '{}'", path.display()))?;
        let mut r = BufReader::new(f);
        let mut magic = [0u8; 8];
        r.read_exact(&mut magic)?;
        if &magic != Self::MAGIC {
            bail!("'{}' is not a dataset cache (bad magic)", path.display());
        }
        let mut u = [0u8; 8];
        let mut next_u64 = |r: &mut BufReader<File>| -> Result<usize> {
            r.read_exact(&mut u)?;
            Ok(u64::from_le_bytes(u) as usize)
        };
        let (n, height, width) = (next_u64(&mut r)?, next_u64(&mut r)?, next_u64(&mut r)?);
        let read_f32 = |r: &mut BufReader<File>, count: usize| -> Result<Vec<f32>> {
            let mut bytes = vec![0u8; count * 4];
            r.read_exact(&mut bytes)
                .with_context(|| format!("'{}' is truncated", path.display()))?;
            Ok(bytes
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect())
        };
        let elevation_rad = read_f32(&mut r, height * width)?;
        let azimuth_rad = read_f32(&mut r, height * width)?;
        let images = read_f32(&mut r, n * height * width)?;
        Ok(Self {
            height,
            width,
            images,
            angles: AngleGrid {
                height,
                width,
                elevation_rad,
                azimuth_rad,
            },
        })
    }

    /// Load the cache at `cache`, or build it from `files` and write it.
    pub fn load_or_build(cache: &Path, files: &[PathBuf], width: usize) -> Result<Self> {
        if cache.exists() {
            return Self::load(cache);
        }
        let ds = Self::from_kitti_files(files, width)?;
        if let Some(dir) = cache.parent() {
            std::fs::create_dir_all(dir)
                .with_context(|| format!("failed to create '{}'", dir.display()))?;
        }
        ds.save(cache)?;
        Ok(ds)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn network_units_round_trip_and_invalid_is_minus_one() {
        let r = [0.0, 1.0, 1.45, 10.0, 80.0, 81.0];
        let x = range_to_network(&r);
        assert_eq!(x[0], -1.0);
        assert_eq!(x[1], -1.0);
        assert!((x[2] - 1.0).abs() < 1e-6);
        assert_eq!(x[5], -1.0);
        let back = network_to_range(&x);
        assert!((back[3] - 10.0).abs() < 1e-3);
        assert!((back[4] - 80.0).abs() < 1e-2);
        assert_eq!(back[0], 0.0);
    }

    #[test]
    fn cache_round_trip() {
        let grid = SensorProfile::kitti_hdl64e().with_columns(8).angle_grid();
        let ds = RangeDataset {
            height: grid.height,
            width: grid.width,
            images: (0..2 * grid.len())
                .map(|i| (i % 7) as f32 * 0.1 - 0.5)
                .collect(),
            angles: grid,
        };
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("ds.bin");
        ds.save(&path).expect("save");
        assert_eq!(RangeDataset::load(&path).expect("load"), ds);
    }

    #[test]
    fn split_trains_on_every_drive_and_keeps_evaluation_data_out() {
        let root = Path::new("../shared/real_lidar");
        let root = if root.exists() {
            root.to_path_buf()
        } else {
            PathBuf::from("/work/shared/real_lidar")
        };
        if !root.exists() {
            eprintln!("skipping: no real_lidar folder");
            return;
        }
        let train = kitti_training_files(&root).expect("list");
        let held = kitti_heldout_files(&root).expect("list");
        assert!(!train.is_empty() && !held.is_empty());
        let lossy = |f: &PathBuf| f.to_string_lossy().into_owned();
        for f in train.iter().map(lossy) {
            assert!(!f.contains("semantickitti_mini/00/") && !f.contains("semantickitti_mini/07/"));
            for eval in EVALUATION_FOLDERS {
                assert!(!f.contains(eval), "{f} is evaluation data");
            }
        }
        // Every KITTI raw drive, object and odometry folder present is trained on.
        for drive in subdirs(&root).expect("list") {
            let name = dir_name(&drive);
            if name.starts_with(KITTI_RAW_PREFIX)
                || KITTI_VELODYNE_PREFIXES.iter().any(|p| name.starts_with(p))
            {
                let d = lossy(&drive);
                assert!(
                    train.iter().any(|f| lossy(f).starts_with(&d)),
                    "{d} missing"
                );
            }
        }
        assert!(held.iter().all(|f| !train.contains(f)));
    }

    /// Builds a `real_lidar`-shaped folder: drives `a` (3 scans) and `b` (2), an object
    /// folder (2), and mini sequences 00 (held out) and 01 (1 scan each).
    fn fake_real_lidar(root: &Path) {
        let scans = [
            ("kitti_raw_a", 3),
            ("kitti_raw_b", 2),
            ("kitti_object_x/velodyne", 2),
            ("semantickitti_mini/00/velodyne", 1),
            ("semantickitti_mini/01/velodyne", 1),
        ];
        for (dir, n) in scans {
            std::fs::create_dir_all(root.join(dir)).expect("mkdir");
            for i in 0..n {
                std::fs::write(root.join(dir).join(format!("{i:06}.bin")), []).expect("write");
            }
        }
    }

    #[test]
    fn validation_drives_leave_training_and_only_them() {
        let dir = tempfile::tempdir().expect("tempdir");
        fake_real_lidar(dir.path());
        let all = kitti_training_files(dir.path()).expect("list");
        assert_eq!(all.len(), 8);
        let (train, val) =
            kitti_validation_split(dir.path(), &["kitti_raw_b".into()]).expect("split");
        assert_eq!(val.len(), 2);
        assert!(
            val.iter()
                .all(|f| f.starts_with(dir.path().join("kitti_raw_b")))
        );
        assert_eq!(train.len(), 6);
        assert!(train.iter().all(|f| !val.contains(f)));
        let (same, none) = kitti_validation_split(dir.path(), &[]).expect("split");
        assert_eq!((same, none.len()), (all, 0));
    }

    #[test]
    fn a_validation_drive_must_name_a_drive_folder() {
        let dir = tempfile::tempdir().expect("tempdir");
        fake_real_lidar(dir.path());
        for bad in [
            "kitti_raw_zz",
            "semantickitti_mini",
            "kitti_raw_a/../kitti_raw_b",
        ] {
            let err = kitti_validation_split(dir.path(), &[bad.into()]).unwrap_err();
            assert!(
                format!("{err:#}").contains(bad.split('/').next().unwrap()),
                "{err:#}"
            );
        }
        std::fs::remove_dir_all(dir.path().join("semantickitti_mini/01")).expect("rm");
        std::fs::remove_dir_all(dir.path().join("kitti_object_x")).expect("rm");
        let err = kitti_validation_split(dir.path(), &["kitti_raw_a".into(), "kitti_raw_b".into()])
            .unwrap_err();
        assert!(
            format!("{err:#}").contains("no training scans left"),
            "{err:#}"
        );
    }
}
