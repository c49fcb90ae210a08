//! Training data for the GAN: scans projected once onto one sensor's grid as inverse-depth
//! images (network units, no return = -1) and cached in one binary file with that sensor's
//! profile, so training never re-projects. Owns the network units ([`DepthRange`]), the
//! train/held-out split of KITTI's `real_lidar/` folders and the cache format.

use std::fs::File;
use std::io::{BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail, ensure};

use crate::lidar::{self, AngleGrid, SensorProfile, Strategy};

/// Smallest valid depth of KITTI's HDL-64E (the shipped model's range): the scale of its
/// inverse depth x_d = MIN_DEPTH_M / depth.
pub const MIN_DEPTH_M: f32 = 1.45;
/// Largest valid depth of KITTI's HDL-64E.
pub const MAX_DEPTH_M: f32 = 80.0;

/// In network units, a pixel at or below this is a dropped ray (-1), anything above a return.
pub const DROPPED: f32 = -1.0 + 1e-4;

/// The depths a model's network units span: x_d = min / depth, in network units
/// 2 x_d - 1, so the nearest valid return is 1 and a dropped ray -1. A model trained on a
/// sensor uses that sensor's valid range ([`DepthRange::of`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DepthRange {
    pub min_m: f32,
    pub max_m: f32,
}

impl DepthRange {
    /// KITTI's HDL-64E, 1.45-80 m as in the reference preprocessing (the shipped model).
    pub const KITTI: DepthRange = DepthRange {
        min_m: MIN_DEPTH_M,
        max_m: MAX_DEPTH_M,
    };

    /// The valid range of a sensor profile.
    pub fn of(profile: &SensorProfile) -> Self {
        Self {
            min_m: profile.min_range_m,
            max_m: profile.max_range_m,
        }
    }

    pub fn contains(&self, depth_m: f32) -> bool {
        (self.min_m..=self.max_m).contains(&depth_m)
    }

    /// The smallest x_d of a valid return (at the farthest valid depth).
    pub fn x_d_floor(&self) -> f32 {
        self.min_m / self.max_m
    }

    /// Range image (meters, 0 = no return) -> network units: 2 min / depth - 1 for valid
    /// depths, -1 elsewhere.
    pub fn to_network(&self, range_m: &[f32]) -> Vec<f32> {
        range_m
            .iter()
            .map(|&d| {
                if self.contains(d) {
                    2.0 * self.min_m / d - 1.0
                } else {
                    -1.0
                }
            })
            .collect()
    }

    /// Network units -> depth in meters (0 = no return).
    pub fn to_range(&self, x: &[f32]) -> Vec<f32> {
        x.iter().map(|&v| self.depth_of(v)).collect()
    }

    /// Generator output in network units -> depth in meters, clamped to the valid range
    /// (the generator renders every ray, dropped or not).
    pub fn clamped_depths(&self, x: &[f32]) -> Vec<f32> {
        x.iter()
            .map(|v| {
                let x_d = ((v + 1.0) * 0.5).max(self.x_d_floor());
                (self.min_m / x_d).clamp(self.min_m, self.max_m)
            })
            .collect()
    }

    /// One pixel of [`Self::to_range`].
    pub fn depth_of(&self, v: f32) -> f32 {
        let x_d = (v + 1.0) * 0.5;
        if x_d > self.x_d_floor() * 0.5 {
            self.min_m / x_d
        } else {
            0.0
        }
    }
}

/// [`DepthRange::to_network`] in KITTI's range (the shipped model's units).
pub fn range_to_network(range_m: &[f32]) -> Vec<f32> {
    DepthRange::KITTI.to_network(range_m)
}

/// [`DepthRange::to_range`] in KITTI's range (the shipped model's units).
pub fn network_to_range(x: &[f32]) -> Vec<f32> {
    DepthRange::KITTI.to_range(x)
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
    let mini = real_lidar.join("semantickitti_mini");
    for seq in if mini.is_dir() {
        subdirs(&mini)?
    } else {
        Vec::new()
    } {
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

/// Images in network units, `[n, H, W]` row-major, on one shared angle grid: the grid of
/// `profile` (the sensor they were recorded or simulated with, at the training columns),
/// whose valid range sets the units ([`DepthRange::of`]).
#[derive(Debug, Clone, PartialEq)]
pub struct RangeDataset {
    pub height: usize,
    pub width: usize,
    pub images: Vec<f32>,
    pub angles: AngleGrid,
    pub profile: SensorProfile,
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

    /// The network units of these images.
    pub fn depth_range(&self) -> DepthRange {
        DepthRange::of(&self.profile)
    }

    /// Project KITTI `.bin` scans with the HDL-64E profile at `width` columns (in parallel,
    /// in file order). A scan that cannot be read or projected fails the whole build, naming
    /// the file.
    pub fn from_kitti_files(files: &[PathBuf], width: usize) -> Result<Self> {
        use rayon::prelude::*;
        let profile = SensorProfile::kitti_hdl64e().with_columns(width);
        let angles = profile.angle_grid();
        let units = DepthRange::of(&profile);
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
                Ok(units.to_network(&image.range_m))
            })
            .collect::<Result<_>>()?;
        Ok(Self::from_images(profile, angles, per_file.concat()))
    }

    /// A dataset from images in network units of `profile`'s range on `angles`' grid,
    /// `[n, H, W]` row-major.
    pub fn from_images(profile: SensorProfile, angles: AngleGrid, images: Vec<f32>) -> Self {
        debug_assert_eq!(images.len() % angles.len().max(1), 0);
        Self {
            height: angles.height,
            width: angles.width,
            images,
            angles,
            profile,
        }
    }

    const MAGIC: &'static [u8; 8] = b"RGDSv002";
    /// Caches written before the profile was recorded: KITTI's HDL-64E at their width.
    const MAGIC_V1: &'static [u8; 8] = b"RGDSv001";

    /// Write the cache: magic, the profile as JSON (u64 LE length first), n, H, W (u64 LE),
    /// elevation, azimuth, images (f32 LE).
    pub fn save(&self, path: &Path) -> Result<()> {
        let tmp = path.with_extension("tmp");
        {
            let f = File::create(&tmp)
                .with_context(|| format!("failed to create '{}'", tmp.display()))?;
            let mut w = BufWriter::new(f);
            w.write_all(Self::MAGIC)?;
            let profile = serde_json::to_vec(&self.profile)?;
            w.write_all(&(profile.len() as u64).to_le_bytes())?;
            w.write_all(&profile)?;
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
        let mut u = [0u8; 8];
        let mut next_u64 = |r: &mut BufReader<File>| -> Result<usize> {
            r.read_exact(&mut u)
                .with_context(|| format!("'{}' is truncated", path.display()))?;
            Ok(u64::from_le_bytes(u) as usize)
        };
        let profile = if &magic == Self::MAGIC {
            let len = next_u64(&mut r)?;
            ensure!(
                len <= 1 << 20,
                "'{}' is not a dataset cache (profile of {len} bytes)",
                path.display()
            );
            let mut json = vec![0u8; len];
            r.read_exact(&mut json)
                .with_context(|| format!("'{}' is truncated", path.display()))?;
            Some(
                serde_json::from_slice::<SensorProfile>(&json)
                    .with_context(|| format!("'{}': bad sensor profile", path.display()))?,
            )
        } else if &magic == Self::MAGIC_V1 {
            None
        } else {
            bail!("'{}' is not a dataset cache (bad magic)", path.display());
        };
        let (n, height, width) = (next_u64(&mut r)?, next_u64(&mut r)?, next_u64(&mut r)?);
        ensure!(
            height.saturating_mul(width).saturating_mul(n.max(1)) <= 1 << 34,
            "'{}' is not a dataset cache ({n} images of {height} x {width})",
            path.display()
        );
        let profile = profile.unwrap_or_else(|| SensorProfile::kitti_hdl64e().with_columns(width));
        ensure!(
            profile.beams() == height && profile.columns == width,
            "'{}': its profile {} ({} x {}) is not its images' grid {height} x {width}",
            path.display(),
            profile.name,
            profile.beams(),
            profile.columns
        );
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
            profile,
        })
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
        let d = DepthRange::KITTI.clamped_depths(&[1.0, -1.0, 0.0]);
        assert!((d[0] - 1.45).abs() < 1e-5 && (d[1] - 80.0).abs() < 1e-3);
        assert!((d[2] - 2.9).abs() < 1e-5);
        let back = network_to_range(&x);
        assert!((back[3] - 10.0).abs() < 1e-3);
        assert!((back[4] - 80.0).abs() < 1e-2);
        assert_eq!(back[0], 0.0);
    }

    #[test]
    fn cache_round_trip() {
        let profile = SensorProfile::builtin("os1-32")
            .expect("os1-32")
            .with_columns(8);
        let grid = profile.angle_grid();
        let images = (0..2 * grid.len())
            .map(|i| (i % 7) as f32 * 0.1 - 0.5)
            .collect();
        let ds = RangeDataset::from_images(profile, grid, images);
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("ds.bin");
        ds.save(&path).expect("save");
        assert_eq!(RangeDataset::load(&path).expect("load"), ds);
    }

    /// A cache written before the profile was recorded reads as KITTI's HDL-64E at its width.
    #[test]
    fn a_version_1_cache_reads_as_the_hdl64e() {
        let profile = SensorProfile::kitti_hdl64e().with_columns(16);
        let grid = profile.angle_grid();
        let images: Vec<f32> = (0..grid.len())
            .map(|i| (i % 5) as f32 * 0.2 - 0.5)
            .collect();
        let mut bytes = b"RGDSv001".to_vec();
        for v in [1u64, 64, 16] {
            bytes.extend(v.to_le_bytes());
        }
        for v in grid
            .elevation_rad
            .iter()
            .chain(&grid.azimuth_rad)
            .chain(&images)
        {
            bytes.extend(v.to_le_bytes());
        }
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("v1.bin");
        std::fs::write(&path, bytes).expect("write");
        let ds = RangeDataset::load(&path).expect("load");
        assert_eq!(ds, RangeDataset::from_images(profile, grid, images));
        assert_eq!(ds.depth_range(), DepthRange::KITTI);
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
