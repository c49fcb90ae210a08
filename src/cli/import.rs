//! `rangegan-mcap import DIR OUT`: a KITTI / SemanticKITTI folder becomes an MCAP of
//! ROS 2 PointCloud2 messages (x, y, z, intensity, ring, label) at 10 Hz, so
//! datasets and recordings go through one path.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{Context, bail};

use super::{GlobalArgs, Outcome};
use crate::io::Family;
use crate::io::encoders::{Kind, encode_cloud};
use crate::lidar::{kitti, projection::ring_order_ids};

#[derive(Debug, clap::Args)]
pub struct ImportArgs {
    /// Dataset folder: holds `velodyne/*.bin` (or the `.bin` files themselves) and
    /// optionally `labels/*.label`.
    pub dir: PathBuf,
    #[command(flatten)]
    pub out: super::CloudOutputArgs,
    /// Leave no OUT and exit 3 if any scan could not be read (otherwise each is a warning
    /// and the other scans are written).
    #[arg(long)]
    pub strict: bool,
}

/// A dataset folder's scans, sorted, each with its label file if present, and
/// warnings for files that cannot take part (label files that match no scan).
struct Dataset {
    scans: Vec<(PathBuf, Option<PathBuf>)>,
    warnings: Vec<String>,
}

fn files_with_extension(dir: &Path, ext: &str) -> anyhow::Result<Vec<PathBuf>> {
    if !dir.is_dir() {
        return Ok(Vec::new());
    }
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("cannot read {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        // Only regular files: a FIFO or device named *.bin would block or never end.
        .filter(|p| p.is_file())
        .filter(|p| p.extension().is_some_and(|e| e.eq_ignore_ascii_case(ext)))
        .collect();
    files.sort();
    Ok(files)
}

/// The scans of `velodyne/*.bin` (or `*.bin` in `dir`), with labels from `labels/` or
/// beside the `.bin` files (SemanticKITTI layouts differ).
fn dataset_files(dir: &Path) -> anyhow::Result<Dataset> {
    let velodyne = if dir.join("velodyne").is_dir() {
        dir.join("velodyne")
    } else {
        dir.to_path_buf()
    };
    let bins = files_with_extension(&velodyne, "bin")?;
    if bins.is_empty() {
        bail!("{}: no .bin scans (expected velodyne/*.bin)", dir.display());
    }
    let mut labels = files_with_extension(&dir.join("labels"), "label")?;
    labels.extend(files_with_extension(&velodyne, "label")?);
    let stem = |p: &Path| p.file_stem().map(|s| s.to_os_string());
    let mut used = vec![false; labels.len()];
    let scans = bins
        .into_iter()
        .map(|bin| {
            let found = labels.iter().position(|l| stem(l) == stem(&bin));
            if let Some(k) = found {
                used[k] = true;
            }
            (bin, found.map(|k| labels[k].clone()))
        })
        .collect();
    let mut warnings: Vec<String> = labels
        .iter()
        .zip(&used)
        .filter(|(_, used)| !**used)
        .map(|(l, _)| {
            format!(
                "{}: no .bin scan of that name; label file not used",
                l.display()
            )
        })
        .collect();
    let scans: Vec<(PathBuf, Option<PathBuf>)> = scans;
    let unlabelled: Vec<_> = scans.iter().filter(|s| s.1.is_none()).collect();
    if !labels.is_empty() && !unlabelled.is_empty() {
        warnings.push(format!(
            "{} of {} scans have no .label file (first: {}); written without labels",
            unlabelled.len(),
            scans.len(),
            unlabelled[0].0.display()
        ));
    }
    Ok(Dataset { scans, warnings })
}

pub fn run(global: &GlobalArgs, args: ImportArgs) -> anyhow::Result<Outcome> {
    let Dataset {
        scans: files,
        mut warnings,
    } = dataset_files(&args.dir)?;
    let inputs: Vec<&Path> = files
        .iter()
        .flat_map(|(bin, label)| std::iter::once(bin.as_path()).chain(label.as_deref()))
        .collect();
    crate::io::writer::refuse_overwriting_inputs(&args.out.output, &inputs)?;
    let start_nanos = args.out.start_nanos(files.len() as u64)?;
    let mut out = args.out.create()?;
    out.write_metadata(
        "rangegan",
        BTreeMap::from([
            ("tool".to_string(), "rangegan-mcap import".to_string()),
            ("version".to_string(), env!("CARGO_PKG_VERSION").to_string()),
            ("source".to_string(), args.dir.display().to_string()),
        ]),
    )?;
    let channel = out.own_channel(&args.out.topic, Family::Ros2, Kind::Cloud)?;
    let bar = super::progress_bar(global, files.len() as u64);
    let mut written = 0u64;
    let mut unreadable = 0usize;
    for (bin, label) in &files {
        let mut scan = match kitti::read_scan(bin, label.as_deref()) {
            Ok(scan) => scan,
            Err(e) => {
                // One bad file does not cost the others (errors name the file).
                warnings.push(format!("{e}; scan not written"));
                unreadable += 1;
                bar.inc(1);
                continue;
            }
        };
        if scan.returns() == 0 {
            warnings.push(format!(
                "{}: no point with a return; scan not written",
                bin.display()
            ));
            bar.inc(1);
            continue;
        }
        // KITTI stores rings one after another; make the ring explicit for every reader.
        scan.ring = Some(
            ring_order_ids(&scan)
                .into_iter()
                .map(|r| r.min(u16::MAX as u32) as u16)
                .collect(),
        );
        let stamp = start_nanos + written * 100_000_000;
        written += 1;
        let msg = encode_cloud(Family::Ros2, stamp, &args.out.frame_id, &scan, &[]);
        out.write_own(channel, stamp, stamp, &msg)?;
        bar.inc(1);
    }
    bar.finish_and_clear();
    for w in &warnings {
        eprintln!("warning: {w}");
    }
    if args.strict && unreadable > 0 {
        out.discard();
        eprintln!(
            "{}: not written (--strict: {unreadable} scans could not be read)",
            args.out.output.display()
        );
        return Ok(Outcome::DataSkipped);
    }
    out.finish()?;
    let labelled = files.iter().filter(|f| f.1.is_some()).count();
    if global.json {
        println!(
            "{}",
            serde_json::json!({ "output": args.out.output, "scans": written, "unreadable": unreadable, "labelled": labelled, "topic": args.out.topic, "warnings": warnings })
        );
    } else if !global.quiet {
        eprintln!(
            "{} -> {}: {} scans ({} labelled) on {}",
            args.dir.display(),
            args.out.output.display(),
            written,
            labelled,
            args.out.topic
        );
    }
    Ok(Outcome::Success)
}
