//! Where the scans of a training run or a calibration come from: KITTI's `real_lidar/`
//! folders (`.bin` scans of the HDL-64E) or MCAP recordings of any sensor, with whole
//! drives or recordings set aside for validation. Every recording is projected onto one
//! sensor grid (the model learns one sensor), chosen as `convert` chooses it: a given
//! profile, or the one estimated from the first recording's first scan.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail, ensure};

use crate::lidar::{RangeImage, SensorProfile, Strategy};
use crate::model::data::{self, DepthRange, RangeDataset};
use crate::recording::{self, Grid};

/// Columns of the KITTI training grid (the shipped model's).
pub const KITTI_COLUMNS: usize = 512;

/// How a recording's clouds become range images (the `convert` flags of the same names).
#[derive(Debug, Clone, Default)]
pub struct Layout {
    /// The point-cloud topic; `None` = each recording's only or first one.
    pub topic: Option<String>,
    /// The sensor; `None` = estimated from the first recording (or its `simulate` record).
    pub sensor: Option<SensorProfile>,
    /// Columns of the grid; `None` = the profile's own (KITTI folders: 512).
    pub columns: Option<usize>,
    pub strategy: Strategy,
}

/// What the scans are.
#[derive(Debug, Clone, PartialEq)]
pub enum Scans {
    /// KITTI `.bin` scans of the HDL-64E.
    Kitti(Vec<PathBuf>),
    /// MCAP recordings, each read whole.
    Recordings(Vec<PathBuf>),
}

impl Scans {
    pub fn is_empty(&self) -> bool {
        match self {
            Scans::Kitti(f) | Scans::Recordings(f) => f.is_empty(),
        }
    }
}

/// The data of a run: a KITTI `real_lidar/` folder, or MCAP files and folders of them.
#[derive(Debug, Clone)]
pub struct ScanSource {
    pub data: Vec<PathBuf>,
    /// KITTI raw drive folder names, or recordings (file name, with or without `.mcap`, or
    /// path), left out of training.
    pub validation: Vec<String>,
    pub layout: Layout,
}

/// Whether `dir` is a KITTI `real_lidar/`-style folder.
fn is_kitti_folder(dir: &Path) -> bool {
    dir.join("semantickitti_mini").is_dir()
        || std::fs::read_dir(dir).is_ok_and(|entries| {
            entries.filter_map(|e| e.ok()).any(|e| {
                let name = e.file_name().to_string_lossy().into_owned();
                name.starts_with(data::KITTI_RAW_PREFIX)
                    || data::KITTI_VELODYNE_PREFIXES
                        .iter()
                        .any(|p| name.starts_with(p))
            })
        })
}

/// The `.mcap` files at `path`: the file itself, or every one under the folder (sorted).
fn mcap_files(path: &Path, out: &mut Vec<PathBuf>) -> Result<()> {
    if path.is_file() {
        out.push(path.to_path_buf());
        return Ok(());
    }
    let mut entries: Vec<PathBuf> = std::fs::read_dir(path)
        .with_context(|| format!("failed to list '{}'", path.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .collect();
    entries.sort();
    for entry in entries {
        if entry.is_dir() {
            mcap_files(&entry, out)?;
        } else if entry.extension().is_some_and(|e| e == "mcap") {
            out.push(entry);
        }
    }
    Ok(())
}

/// Whether `name` (a `--validation-drive` value) names `file`.
fn names_recording(name: &str, file: &Path) -> bool {
    let stem = file.file_stem().and_then(|s| s.to_str());
    let full = file.file_name().and_then(|s| s.to_str());
    Some(name) == stem || Some(name) == full || Path::new(name) == file
}

impl ScanSource {
    /// The training and validation scans.
    pub fn split(&self) -> Result<(Scans, Scans)> {
        ensure!(
            !self.data.is_empty(),
            "no training data: give --data (a KITTI real_lidar folder, or MCAP recordings and folders of them)"
        );
        if let [dir] = self.data.as_slice()
            && dir.is_dir()
            && is_kitti_folder(dir)
        {
            let (train, val) = data::kitti_validation_split(dir, &self.validation)?;
            return Ok((Scans::Kitti(train), Scans::Kitti(val)));
        }
        let mut files = Vec::new();
        for path in &self.data {
            ensure!(
                path.exists(),
                "'{}' does not exist (give MCAP recordings, folders of them, or one KITTI real_lidar folder)",
                path.display()
            );
            ensure!(
                !(path.is_dir() && is_kitti_folder(path)),
                "'{}' is a KITTI folder: give it alone, not beside MCAP recordings",
                path.display()
            );
            mcap_files(path, &mut files)?;
        }
        files.dedup();
        ensure!(
            !files.is_empty(),
            "no MCAP recordings (.mcap) in {}",
            self.data
                .iter()
                .map(|p| format!("'{}'", p.display()))
                .collect::<Vec<_>>()
                .join(", ")
        );
        for name in &self.validation {
            ensure!(
                files.iter().any(|f| names_recording(name, f)),
                "validation recording '{name}' is none of the {} recordings given",
                files.len()
            );
        }
        let (val, train): (Vec<PathBuf>, Vec<PathBuf>) = files
            .into_iter()
            .partition(|f| self.validation.iter().any(|n| names_recording(n, f)));
        ensure!(
            !train.is_empty(),
            "no training recordings left after setting aside {:?}",
            self.validation
        );
        Ok((Scans::Recordings(train), Scans::Recordings(val)))
    }

    /// The training scans of [`Self::split`].
    pub fn training(&self) -> Result<Scans> {
        Ok(self.split()?.0)
    }

    /// The sensor grid these scans are trained on: the given profile, KITTI's HDL-64E for
    /// KITTI folders, or the one estimated from the first recording; at the given columns.
    pub fn profile(&self, scans: &Scans) -> Result<SensorProfile> {
        let base = match (&self.layout.sensor, scans) {
            (Some(p), _) => p.clone(),
            (None, Scans::Kitti(_)) => SensorProfile::kitti_hdl64e().with_columns(KITTI_COLUMNS),
            (None, Scans::Recordings(files)) => {
                let first = files.first().context("no recordings")?;
                let grid = Grid::FromRecording { columns: None };
                recording::read_with(first, self.layout.topic.as_deref(), &grid, Strategy::Auto)?
                    .profile
            }
        };
        Ok(match self.layout.columns {
            Some(c) => base.with_columns(c),
            None => base,
        })
    }

    /// Projects `scans` onto `profile`'s grid as a dataset in its network units. Scans that
    /// could not be decoded or projected are reported on stderr with their file, topic and
    /// time; a recording with none left fails the build.
    pub fn dataset(&self, scans: &Scans, profile: &SensorProfile) -> Result<RangeDataset> {
        match scans {
            Scans::Kitti(files) => {
                ensure!(
                    self.layout.topic.is_none()
                        && profile.elevation_deg == SensorProfile::kitti_hdl64e().elevation_deg,
                    "KITTI folders hold HDL-64E scans without topics: --topic and another --sensor ({}) are for MCAP recordings",
                    profile.name
                );
                RangeDataset::from_kitti_files(files, profile.columns)
            }
            Scans::Recordings(files) => {
                let images = self.recording_images(files, profile)?;
                let profile = &with_valid_range(profile, &images);
                let units = DepthRange::of(profile);
                let pixels = images
                    .iter()
                    .flat_map(|img| units.to_network(&img.range_m))
                    .collect();
                Ok(RangeDataset::from_images(
                    profile.clone(),
                    profile.angle_grid(),
                    pixels,
                ))
            }
        }
    }

    /// `n` of `scans` (evenly spaced, all where there are fewer) on `profile`'s grid.
    pub fn spaced_images(
        &self,
        scans: &Scans,
        profile: &SensorProfile,
        n: usize,
    ) -> Result<Vec<RangeImage>> {
        let spaced = |len: usize| (0..n.min(len)).map(move |i| i * len / n.min(len));
        match scans {
            Scans::Kitti(files) => spaced(files.len())
                .map(|i| {
                    let path = &files[i];
                    let scan = crate::lidar::kitti::read_bin(path)
                        .with_context(|| format!("failed to read '{}'", path.display()))?;
                    crate::lidar::project(&scan, profile, Strategy::Auto)
                        .with_context(|| format!("failed to project '{}'", path.display()))
                })
                .collect(),
            Scans::Recordings(files) => {
                let all = self.recording_images(files, profile)?;
                let keep: Vec<usize> = spaced(all.len()).collect();
                Ok(all
                    .into_iter()
                    .enumerate()
                    .filter(|(i, _)| keep.binary_search(i).is_ok())
                    .map(|(_, image)| image)
                    .collect())
            }
        }
    }

    /// Every scan of `files` on `profile`'s grid, in file order.
    pub fn recording_images(
        &self,
        files: &[PathBuf],
        profile: &SensorProfile,
    ) -> Result<Vec<RangeImage>> {
        let grid = Grid::Fixed(profile.clone());
        let mut images = Vec::new();
        for file in files {
            let rec = recording::read_with(
                file,
                self.layout.topic.as_deref(),
                &grid,
                self.layout.strategy,
            )?;
            if let Some(own) = &rec.own_sensor
                && recording::other_sensors(own, profile)
            {
                bail!(
                    "{} was made by a {}-beam sensor ({}), the scans are trained on a {}-beam grid ({}): one model learns one sensor's scans; give the recordings of one sensor",
                    file.display(),
                    own.beams(),
                    own.name,
                    profile.beams(),
                    profile.name
                );
            }
            for skipped in &rec.skipped {
                eprintln!("warning: left out of the training scans: {skipped}");
            }
            images.extend(rec.images);
        }
        Ok(images)
    }

    /// The dataset cache at `cache`, or the training scans projected into it (written
    /// atomically). The cache records its profile, so a resumed run needs no scans.
    pub fn load_or_build(&self, cache: &Path) -> Result<RangeDataset> {
        if cache.exists() {
            return RangeDataset::load(cache);
        }
        let scans = self.training()?;
        let profile = self.profile(&scans)?;
        let dataset = self.dataset(&scans, &profile)?;
        if dataset.is_empty() {
            bail!("no training scans");
        }
        if let Some(dir) = cache.parent() {
            std::fs::create_dir_all(dir)
                .with_context(|| format!("failed to create '{}'", dir.display()))?;
        }
        dataset.save(cache)?;
        Ok(dataset)
    }
}

/// `profile` with a valid range to train in: its own, or where it has none (an estimated
/// profile keeps every return: 0 m and up), the span of the returns in `images`, so the
/// network units start at the nearest return the sensor gave.
fn with_valid_range(profile: &SensorProfile, images: &[RangeImage]) -> SensorProfile {
    let mut profile = profile.clone();
    if profile.min_range_m > 0.0 {
        return profile;
    }
    let (lo, hi) = images
        .iter()
        .flat_map(|img| img.range_m.iter().copied())
        .filter(|&r| r > 0.0 && r.is_finite())
        .fold((f32::INFINITY, 0.0f32), |(lo, hi), r| {
            (lo.min(r), hi.max(r))
        });
    if lo.is_finite() {
        profile.min_range_m = ((lo * 100.0).floor() / 100.0).max(MIN_TRAINING_RANGE_M);
        profile.max_range_m = ((hi * 100.0).ceil() / 100.0).max(profile.min_range_m * 2.0);
    }
    if profile.name == "auto" {
        profile.name = format!("estimated-{}", profile.beams());
    }
    profile
}

/// The nearest depth a model's units may start at: x_d = min / depth must stay a usable scale.
const MIN_TRAINING_RANGE_M: f32 = 0.05;

/// The dataset cache at `cache`, built from `source` where it is missing.
pub fn load_dataset(cache: &Path, source: Option<&ScanSource>) -> Result<RangeDataset> {
    match source {
        Some(source) => source.load_or_build(cache),
        None if cache.exists() => RangeDataset::load(cache),
        None => bail!(
            "no dataset cache at '{}' and no scans to build it from (give --data)",
            cache.display()
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn source(data: Vec<PathBuf>, validation: &[&str]) -> ScanSource {
        ScanSource {
            data,
            validation: validation.iter().map(|s| s.to_string()).collect(),
            layout: Layout::default(),
        }
    }

    #[test]
    fn recordings_are_found_in_folders_and_a_named_one_is_held_out() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(dir.path().join("day2")).unwrap();
        for f in ["a.mcap", "day2/b.mcap", "day2/notes.txt"] {
            std::fs::write(dir.path().join(f), b"").unwrap();
        }
        let (train, val) = source(vec![dir.path().into()], &["b"]).split().unwrap();
        assert_eq!(train, Scans::Recordings(vec![dir.path().join("a.mcap")]));
        assert_eq!(val, Scans::Recordings(vec![dir.path().join("day2/b.mcap")]));
        let err = source(vec![dir.path().into()], &["c.mcap"])
            .split()
            .unwrap_err();
        assert!(
            err.to_string().contains("'c.mcap' is none of the 2"),
            "{err}"
        );
        let err = source(vec![dir.path().into()], &["a", "b.mcap"])
            .split()
            .unwrap_err();
        assert!(err.to_string().contains("no training recordings"), "{err}");
    }

    /// An estimated profile (0 m and up) trains in the span of the returns it was given; a
    /// profile with its own range keeps it.
    #[test]
    fn an_estimated_profile_trains_in_the_range_of_its_returns() {
        let mut estimated = SensorProfile::builtin("os1-32").unwrap().with_columns(4);
        (estimated.name, estimated.min_range_m) = ("auto".into(), 0.0);
        let mut image = RangeImage::empty(estimated.angle_grid());
        image.range_m[0] = 0.734;
        image.range_m[5] = 41.2;
        let fitted = with_valid_range(&estimated, &[image.clone()]);
        assert_eq!((fitted.min_range_m, fitted.max_range_m), (0.73, 41.2));
        assert_eq!(fitted.name, "estimated-32");
        let builtin = SensorProfile::builtin("os1-32").unwrap();
        assert_eq!(with_valid_range(&builtin, &[image]), builtin);
    }

    #[test]
    fn missing_or_empty_data_is_refused_by_name() {
        let dir = tempfile::tempdir().unwrap();
        let err = source(vec![], &[]).split().unwrap_err();
        assert!(err.to_string().contains("give --data"), "{err}");
        let gone = dir.path().join("nothing-here");
        let err = source(vec![gone], &[]).split().unwrap_err();
        assert!(err.to_string().contains("nothing-here"), "{err}");
        let err = source(vec![dir.path().into()], &[]).split().unwrap_err();
        assert!(err.to_string().contains("no MCAP recordings"), "{err}");
    }

    #[test]
    fn a_kitti_folder_is_read_as_kitti_and_only_alone() {
        let dir = tempfile::tempdir().unwrap();
        let kitti = dir.path().join("real_lidar");
        std::fs::create_dir_all(kitti.join("kitti_raw_a")).unwrap();
        std::fs::write(kitti.join("kitti_raw_a/000000.bin"), b"").unwrap();
        let (train, val) = source(vec![kitti.clone()], &[]).split().unwrap();
        assert_eq!(
            train,
            Scans::Kitti(vec![kitti.join("kitti_raw_a/000000.bin")])
        );
        assert!(val.is_empty());
        std::fs::write(dir.path().join("x.mcap"), b"").unwrap();
        let err = source(vec![dir.path().join("x.mcap"), kitti], &[])
            .split()
            .unwrap_err();
        assert!(err.to_string().contains("give it alone"), "{err}");
    }
}
