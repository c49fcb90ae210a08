//! `rangegan-mcap import DIR OUT`: a folder of scans becomes an MCAP of ROS 2 PointCloud2
//! messages at 10 Hz, so datasets and recordings go through one path. KITTI / SemanticKITTI
//! `.bin` scans (x, y, z, intensity, their ring order made a ring field, labels), nuScenes
//! `.pcd.bin` scans (with their ring field) and `.pcd` files (ASCII or binary, any sensor,
//! with the fields they hold). Labels come from SemanticKITTI `labels/*.label` files, or from
//! KITTI object boxes (`label_2/` with `calib/`) as the partial labels of [`kitti_boxes`].
//! An Ouster PCAP capture with its metadata JSON becomes one organized cloud per rotation
//! ([`ouster_pcap`]).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{Context, bail};

use super::{GlobalArgs, Outcome};
use crate::io::Family;
use crate::io::encoders::{Kind, encode_cloud};
use crate::lidar::{
    Scan, kitti, kitti_boxes, nuscenes, ouster_pcap, pcd, projection::ring_order_ids,
};

#[derive(Debug, clap::Args)]
pub struct ImportArgs {
    /// Dataset folder: holds KITTI scans in `velodyne/*.bin` (or the `.bin` files themselves)
    /// and optionally `labels/*.label`, or KITTI object boxes in `label_2/*.txt` with
    /// `calib/*.txt` (cars and pedestrians labelled, the rest of the camera's view marked as
    /// neither); or nuScenes `*.pcd.bin` scans; or `*.pcd` files of any sensor. Scans are
    /// written in file-name order. Or an Ouster PCAP capture (`.pcap`, legacy or eUDP
    /// packets): one organized cloud per rotation, in capture order.
    pub dir: PathBuf,
    /// The Ouster capture's metadata JSON (default: the `.json` beside the `.pcap` with its
    /// name's start, or the only `.json` in its folder).
    #[arg(long)]
    pub metadata: Option<PathBuf>,
    #[command(flatten)]
    pub out: super::CloudOutputArgs,
    /// Leave no OUT and exit 3 if any scan could not be read (otherwise each is a warning
    /// and the other scans are written).
    #[arg(long)]
    pub strict: bool,
}

/// Where a scan's labels come from.
#[derive(Debug, Clone)]
enum Labels {
    /// A SemanticKITTI `.label` file.
    Semantic(PathBuf),
    /// KITTI object boxes and the frame's calibration.
    Boxes { label_2: PathBuf, calib: PathBuf },
}

impl Labels {
    fn files(&self) -> Vec<&Path> {
        match self {
            Labels::Semantic(p) => vec![p],
            Labels::Boxes { label_2, calib } => vec![label_2, calib],
        }
    }

    fn attach(&self, bin: &Path) -> Result<crate::lidar::Scan, kitti::KittiError> {
        match self {
            Labels::Semantic(path) => kitti::read_scan(bin, Some(path)),
            Labels::Boxes { label_2, calib } => {
                let mut scan = kitti::read_bin(bin)?;
                scan.label = Some(kitti_boxes::read_point_labels(&scan.xyz, label_2, calib)?);
                Ok(scan)
            }
        }
    }
}

/// A dataset folder's scans, sorted, each with its labels if present, and
/// warnings for files that cannot take part (label files that match no scan).
struct Dataset {
    format: ScanFormat,
    scans: Vec<(PathBuf, Option<Labels>)>,
    warnings: Vec<String>,
}

/// How a folder's scans are stored.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum ScanFormat {
    /// KITTI `.bin`: float32 x, y, z, reflectance, ring after ring.
    Kitti,
    /// nuScenes `.pcd.bin`: float32 x, y, z, intensity, ring.
    NuScenes,
    /// Point Cloud Data files.
    Pcd,
}

impl ScanFormat {
    /// Reads one scan, with what a user should know about it; KITTI's ring order becomes a
    /// ring field.
    fn read(
        self,
        path: &Path,
        labels: Option<&Labels>,
    ) -> anyhow::Result<(crate::lidar::Scan, Vec<String>)> {
        Ok(match self {
            ScanFormat::Kitti => {
                let mut scan = match labels {
                    Some(labels) => labels.attach(path)?,
                    None => kitti::read_bin(path)?,
                };
                // KITTI stores rings one after another; make the ring explicit for every reader.
                scan.ring = Some(
                    ring_order_ids(&scan)
                        .into_iter()
                        .map(|r| r.min(u16::MAX as u32) as u16)
                        .collect(),
                );
                (scan, Vec::new())
            }
            ScanFormat::NuScenes => (nuscenes::read_bin(path)?, Vec::new()),
            ScanFormat::Pcd => pcd::read_pcd_noted(path)?,
        })
    }
}

fn is_nuscenes(p: &Path) -> bool {
    p.to_string_lossy()
        .to_ascii_lowercase()
        .ends_with(".pcd.bin")
}

/// The folder's nuScenes or PCD scans, when it holds no KITTI `.bin`; an error when it
/// holds scans of more than one kind.
fn other_format(
    dir: &Path,
    bins: &[PathBuf],
) -> anyhow::Result<Option<(ScanFormat, Vec<PathBuf>)>> {
    let nus: Vec<PathBuf> = bins.iter().filter(|p| is_nuscenes(p)).cloned().collect();
    let pcds = files_with_extension(dir, "pcd")?;
    let kitti = bins.len() - nus.len();
    let kinds = [
        (kitti, ".bin (KITTI)"),
        (nus.len(), ".pcd.bin (nuScenes)"),
        (pcds.len(), ".pcd"),
    ];
    let present: Vec<&str> = kinds
        .iter()
        .filter(|(n, _)| *n > 0)
        .map(|(_, k)| *k)
        .collect();
    if present.len() > 1 {
        bail!(
            "{}: holds scans of more than one kind ({}); import each kind from a folder of its own",
            dir.display(),
            present.join(", ")
        );
    }
    Ok(match (nus.is_empty(), pcds.is_empty()) {
        (false, _) => Some((ScanFormat::NuScenes, nus)),
        (true, false) => Some((ScanFormat::Pcd, pcds)),
        (true, true) => None,
    })
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

/// `.bin` files in the subfolders of `dir` (at any depth, symlinked folders not followed):
/// not scans of this dataset, but worth a word, since a user may have meant them.
fn nested_bins(dir: &Path) -> Vec<PathBuf> {
    let mut found = Vec::new();
    let mut todo: Vec<PathBuf> = Vec::new();
    let subdirs = |d: &Path| -> Vec<PathBuf> {
        std::fs::read_dir(d)
            .map(|it| {
                it.filter_map(|e| e.ok())
                    .filter(|e| e.file_type().is_ok_and(|t| t.is_dir()))
                    .map(|e| e.path())
                    .collect()
            })
            .unwrap_or_default()
    };
    todo.extend(subdirs(dir));
    // Bounded: a deep tree is reported by its first files, not walked to its end.
    while let Some(d) = todo.pop()
        && found.len() < 10_000
    {
        found.extend(files_with_extension(&d, "bin").unwrap_or_default());
        todo.extend(subdirs(&d));
    }
    found.sort();
    found
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
    if let Some((format, files)) = other_format(&velodyne, &bins)? {
        let scans = files.into_iter().map(|f| (f, None)).collect();
        return Ok(Dataset {
            format,
            scans,
            warnings: Vec::new(),
        });
    }
    if bins.is_empty() {
        bail!(
            "{}: no scans (expected KITTI velodyne/*.bin, nuScenes *.pcd.bin or *.pcd files)",
            dir.display()
        );
    }
    let mut labels = files_with_extension(&dir.join("labels"), "label")?;
    labels.extend(files_with_extension(&velodyne, "label")?);
    let boxes = files_with_extension(&dir.join("label_2"), "txt")?;
    let calibs = files_with_extension(&dir.join("calib"), "txt")?;
    let stem = |p: &Path| p.file_stem().map(|s| s.to_os_string());
    let find = |files: &[PathBuf], bin: &Path| files.iter().position(|l| stem(l) == stem(bin));
    let mut used = vec![false; labels.len()];
    let scans = bins
        .into_iter()
        .map(|bin| {
            let semantic = find(&labels, &bin).map(|k| {
                used[k] = true;
                Labels::Semantic(labels[k].clone())
            });
            let boxed = || {
                let (b, c) = (find(&boxes, &bin)?, find(&calibs, &bin)?);
                Some(Labels::Boxes {
                    label_2: boxes[b].clone(),
                    calib: calibs[c].clone(),
                })
            };
            let found = semantic.or_else(boxed);
            (bin, found)
        })
        .collect::<Vec<_>>();
    let nested = nested_bins(&velodyne);
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
    if let Some(first) = nested.first() {
        warnings.push(format!(
            "{} .bin files in subfolders of {} are not read (first: {}); import each folder on its own",
            nested.len(),
            velodyne.display(),
            first.display()
        ));
    }
    let unlabelled: Vec<_> = scans.iter().filter(|s| s.1.is_none()).collect();
    let any_labels = !(labels.is_empty() && boxes.is_empty());
    if any_labels && !unlabelled.is_empty() {
        warnings.push(format!(
            "{} of {} scans have no labels (a .label file, or label_2 and calib files; first: {}); written without labels",
            unlabelled.len(),
            scans.len(),
            unlabelled[0].0.display()
        ));
    }
    Ok(Dataset {
        format: ScanFormat::Kitti,
        scans,
        warnings,
    })
}

/// One scan to write, or why it cannot be.
struct Item {
    /// The file (and frame) it came from, for warnings.
    source: String,
    scan: anyhow::Result<Scan>,
    labelled: bool,
    /// What a user should know about a scan that is written anyway.
    warning: Option<String>,
}

pub fn run(global: &GlobalArgs, args: ImportArgs) -> anyhow::Result<Outcome> {
    if args.dir.extension().is_some_and(|e| e == "pcap") {
        return run_pcap(global, &args);
    }
    anyhow::ensure!(
        args.metadata.is_none(),
        "--metadata is for Ouster PCAP captures; '{}' is a folder",
        args.dir.display()
    );
    let Dataset {
        format,
        scans: files,
        warnings,
    } = dataset_files(&args.dir)?;
    let inputs: Vec<&Path> = files
        .iter()
        .flat_map(|(bin, labels)| {
            std::iter::once(bin.as_path()).chain(labels.iter().flat_map(Labels::files))
        })
        .collect();
    crate::io::writer::refuse_overwriting_inputs(&args.out.output, &inputs)?;
    let items = files.iter().map(|(bin, label)| {
        let (scan, notes) = match format.read(bin, label.as_ref()) {
            Ok((scan, notes)) => (Ok(scan), notes),
            Err(e) => (Err(e), Vec::new()),
        };
        Item {
            source: bin.display().to_string(),
            scan,
            labelled: label.is_some(),
            warning: (!notes.is_empty()).then(|| notes.join("; ")),
        }
    });
    let own = files
        .first()
        .and_then(|(first, _)| own_start_secs(&args.dir, first));
    write(global, &args, files.len(), items, warnings, own, 0)
}

/// The first scan's own time, where the files carry one: the first line of a KITTI drive's
/// `timestamps.txt` (in the folder, or in the `velodyne_points` folder above `data/`), or the
/// microseconds that end a nuScenes file name (`..._1532402927647951.pcd.bin`).
fn own_start_secs(dir: &Path, first: &Path) -> Option<f64> {
    let candidates = [dir.join("timestamps.txt"), dir.join("../timestamps.txt")];
    if let Some(text) = candidates
        .iter()
        .find_map(|p| std::fs::read_to_string(p).ok())
    {
        return text.lines().next().and_then(crate::util::time::parse_utc);
    }
    let name = first.file_name()?.to_str()?;
    let stem = name.strip_suffix(".pcd.bin")?;
    let micros = stem.rsplit('_').next()?;
    (micros.len() == 16 && micros.bytes().all(|b| b.is_ascii_digit()))
        .then(|| micros.parse::<u64>().ok())
        .flatten()
        .map(|us| us as f64 / 1e6)
}

/// The metadata JSON of an Ouster capture: `--metadata`, else the `.json` beside it whose
/// name starts its name (`OS-1-128_v2.3.0_1024x10.json` for `..._1024x10_lb_n3.pcap`), else
/// the only `.json` in its folder.
fn ouster_metadata_path(pcap: &Path, given: Option<&Path>) -> anyhow::Result<PathBuf> {
    if let Some(p) = given {
        return Ok(p.to_path_buf());
    }
    let dir = pcap
        .parent()
        .filter(|d| !d.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let jsons = files_with_extension(dir, "json")?;
    let stem = pcap.file_stem().and_then(|s| s.to_str()).unwrap_or("");
    let prefixed: Vec<&PathBuf> = jsons
        .iter()
        .filter(|j| {
            j.file_stem()
                .and_then(|s| s.to_str())
                .is_some_and(|s| stem.starts_with(s))
        })
        .collect();
    match (prefixed.as_slice(), jsons.as_slice()) {
        ([one], _) => Ok((*one).clone()),
        ([], [one]) => Ok(one.clone()),
        _ => bail!(
            "{}: which metadata JSON is the capture's? {} in '{}'; give --metadata",
            pcap.display(),
            if jsons.is_empty() {
                "none".to_string()
            } else {
                format!("{} candidates", jsons.len())
            },
            dir.display()
        ),
    }
}

/// `import CAPTURE.pcap`: every rotation of an Ouster capture, partial ones with a warning.
fn run_pcap(global: &GlobalArgs, args: &ImportArgs) -> anyhow::Result<Outcome> {
    let meta_path = ouster_metadata_path(&args.dir, args.metadata.as_deref())?;
    crate::io::writer::refuse_overwriting_inputs(&args.out.output, &[&args.dir, &meta_path])?;
    let text = std::fs::read_to_string(&meta_path)
        .with_context(|| format!("failed to read '{}'", meta_path.display()))?;
    let meta = ouster_pcap::OusterMetadata::from_json(&text)
        .with_context(|| format!("'{}'", meta_path.display()))?;
    let size = std::fs::metadata(&args.dir)
        .with_context(|| format!("cannot open '{}'", args.dir.display()))?
        .len();
    anyhow::ensure!(
        size <= MAX_CAPTURE_BYTES,
        "'{}' is {size} bytes; captures of at most {MAX_CAPTURE_BYTES} are read whole (split it, e.g. `editcap -c 100000`)",
        args.dir.display()
    );
    let bytes = std::fs::read(&args.dir)
        .with_context(|| format!("failed to read '{}'", args.dir.display()))?;
    let in_capture = |e: ouster_pcap::OusterError| anyhow::anyhow!("'{}': {e}", args.dir.display());
    // A first pass counts the rotations and reports the damage: a bad packet is skipped, and
    // damage to the capture's records keeps the rotation in progress as a partial rotation
    // and ends the capture there. The second pass decodes them one at a time, so one frame
    // is in memory at once.
    let mut total = 0usize;
    let mut lost = 0usize;
    let mut beyond = (0usize, 0usize);
    let mut warnings = Vec::new();
    let mut first = ouster_pcap::frames(&bytes, &meta).map_err(in_capture)?;
    for frame in first.by_ref() {
        match frame {
            Ok(frame) => {
                total += 1;
                if frame.columns_beyond > 0 {
                    beyond = (beyond.0 + frame.columns_beyond, beyond.1 + 1);
                }
            }
            Err(e) => {
                lost += 1;
                let after = if e.ends_capture() {
                    "the rotation in progress there is kept as a partial rotation; nothing after it can be read"
                } else {
                    "the packet is skipped"
                };
                warnings.push(format!("{}; {after}", in_capture(e)));
            }
        }
    }
    warnings.extend(
        first
            .port_mismatch()
            .map(|m| format!("'{}': {m}", args.dir.display())),
    );
    if beyond.0 > 0 {
        lost += 1;
        warnings.push(format!(
            "'{}': {} columns in {} rotations carry a measurement id at or past the metadata's columns_per_frame {} ('{}' does not match this capture: its lidar_mode?); their returns are not written",
            args.dir.display(),
            beyond.0,
            beyond.1,
            meta.columns_per_frame,
            meta_path.display()
        ));
    }
    let items = ouster_pcap::frames(&bytes, &meta)
        .map_err(in_capture)?
        .filter_map(Result::ok)
        .map(|frame| {
            let source = format!("{} frame {}", args.dir.display(), frame.frame_id);
            let warning = (!frame.is_complete()).then(|| {
                format!(
                    "{source}: {} of its {} columns were captured (a partial rotation); written as it is",
                    frame.columns_seen, frame.columns
                )
            });
            Item {
                source,
                scan: Ok(frame.scan),
                labelled: false,
                warning,
            }
        });
    write(global, args, total, items, warnings, None, lost)
}

/// The largest Ouster capture `import` reads (it is read whole).
const MAX_CAPTURE_BYTES: u64 = 4 << 30;

/// Writes `items` (of `total`) as PointCloud2 messages at 10 Hz; unreadable and empty scans
/// are warnings, as is data `lost` before the items (damaged packets, say): with `--strict`,
/// either means no output and exit 3.
fn write(
    global: &GlobalArgs,
    args: &ImportArgs,
    total: usize,
    items: impl Iterator<Item = Item>,
    mut warnings: Vec<String>,
    own_start_secs: Option<f64>,
    lost: usize,
) -> anyhow::Result<Outcome> {
    let start_nanos = args.out.start_nanos(total as u64, own_start_secs)?;
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
    let bar = super::progress_bar(global, total as u64);
    let mut written = 0u64;
    let mut labelled = 0u64;
    let mut unreadable = 0usize;
    for item in items {
        bar.inc(1);
        warnings.extend(item.warning);
        let scan = match item.scan {
            Ok(scan) => scan,
            Err(e) => {
                // One bad file does not cost the others (errors name the file).
                warnings.push(format!("{e:#}; scan not written"));
                unreadable += 1;
                continue;
            }
        };
        if scan.returns() == 0 {
            warnings.push(format!(
                "{}: no point with a return; scan not written",
                item.source
            ));
            continue;
        }
        let stamp = start_nanos + written * 100_000_000;
        written += 1;
        labelled += u64::from(item.labelled);
        let msg = encode_cloud(Family::Ros2, stamp, &args.out.frame_id, &scan, &[]);
        out.write_own(channel, stamp, stamp, &msg)?;
    }
    bar.finish_and_clear();
    for w in &warnings {
        eprintln!("warning: {w}");
    }
    if written == 0 {
        out.discard();
        let why = if warnings.is_empty() {
            "it holds no lidar data"
        } else {
            "see the warnings above"
        };
        bail!(
            "{}: none of its {total} scans could be written ({why}); no output",
            args.dir.display(),
        );
    }
    if args.strict && unreadable + lost > 0 {
        out.discard();
        eprintln!(
            "{}: not written (--strict: {unreadable} scans could not be read, {lost} damaged parts of the input)",
            args.out.output.display()
        );
        return Ok(Outcome::DataSkipped);
    }
    out.finish()?;
    if global.json {
        println!(
            "{}",
            serde_json::json!({ "output": args.out.output.display().to_string(), "scans": written, "unreadable": unreadable, "labelled": labelled, "topic": args.out.topic, "warnings": warnings })
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
