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
}

/// The scans of a dataset folder, sorted, each with its label file if present.
fn dataset_files(dir: &Path) -> anyhow::Result<Vec<(PathBuf, Option<PathBuf>)>> {
    let velodyne = if dir.join("velodyne").is_dir() {
        dir.join("velodyne")
    } else {
        dir.to_path_buf()
    };
    let labels = dir.join("labels");
    let mut bins: Vec<PathBuf> = std::fs::read_dir(&velodyne)
        .with_context(|| format!("cannot read {}", velodyne.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "bin"))
        .collect();
    bins.sort();
    if bins.is_empty() {
        bail!("{}: no .bin scans (expected velodyne/*.bin)", dir.display());
    }
    Ok(bins
        .into_iter()
        .map(|bin| {
            let label = bin
                .file_stem()
                .map(|s| labels.join(s).with_extension("label"))
                .filter(|l| l.exists());
            (bin, label)
        })
        .collect())
}

pub fn run(global: &GlobalArgs, args: ImportArgs) -> anyhow::Result<Outcome> {
    let files = dataset_files(&args.dir)?;
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
    let start_nanos = args.out.start_nanos()?;
    for (i, (bin, label)) in files.iter().enumerate() {
        let mut scan = kitti::read_scan(bin, label.as_deref())?;
        // KITTI stores rings one after another; make the ring explicit for every reader.
        scan.ring = Some(
            ring_order_ids(&scan)
                .into_iter()
                .map(|r| r.min(u16::MAX as u32) as u16)
                .collect(),
        );
        let stamp = start_nanos + i as u64 * 100_000_000;
        let msg = encode_cloud(Family::Ros2, stamp, &args.out.frame_id, &scan, &[]);
        out.write_own(channel, stamp, stamp, &msg)?;
        bar.inc(1);
    }
    bar.finish_and_clear();
    out.finish()?;
    let labelled = files.iter().filter(|f| f.1.is_some()).count();
    if global.json {
        println!(
            "{}",
            serde_json::json!({ "output": args.out.output, "scans": files.len(), "labelled": labelled, "topic": args.out.topic })
        );
    } else if !global.quiet {
        eprintln!(
            "{} -> {}: {} scans ({} labelled) on {}",
            args.dir.display(),
            args.out.output.display(),
            files.len(),
            labelled,
            args.out.topic
        );
    }
    Ok(Outcome::Success)
}
