//! Completion of dropped rays as users get it from `convert`: held-out KITTI scans with holes
//! of several kinds cut into them (single pixels; small, medium and large patches; whole
//! beams; an azimuth sector; object-shaped holes), converted by the built binary, and the
//! `depth` and `x_d` channels scored on every hole pixel whose truth has a return, beside
//! interpolating the degraded scan along its rows, along its columns, and the better of the
//! two per kind of hole.
//!
//!     cargo build --release
//!     cargo run --release --example completion_eval -- [--data ../shared/real_lidar]
//!         [--set heldout|validation] [--kinds pixels,small,...] [--bin BINARY]
//!         [-- CONVERT FLAGS...]
//!
//! `validation` (every third scan of the validation drive) is where settings are chosen;
//! `heldout` (the 26 held-out scans) is where they are reported. Flags after `--` go to
//! `convert` (e.g. `--upsample-method gan` for the decoded scene alone in the holes).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use rangegan_mcap::io::roundtrip;
use rangegan_mcap::lidar::{self, RangeImage, Scan, SensorProfile, Strategy};
use rangegan_mcap::model::data::{kitti_heldout_files, kitti_validation_split};

const TOPIC: &str = "/velodyne_points";
const KINDS: [&str; 7] = [
    "pixels", "small", "medium", "large", "beams", "sector", "objects",
];

/// SplitMix64, seeded from the scan and the kind of hole.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
}

/// The scans of `set`, projected onto the 64 x 512 model grid (1.45-80 m).
fn load(data: &Path, set: &str) -> Result<Vec<(String, RangeImage)>> {
    let files: Vec<PathBuf> = match set {
        "validation" => {
            let (_, files) = kitti_validation_split(data, &["kitti_raw_drive_d".to_string()])?;
            files.into_iter().step_by(3).collect()
        }
        "heldout" => {
            let mut files = Vec::new();
            for dir in ["semantickitti_ssv3", "patchworkpp"] {
                let mut found: Vec<PathBuf> = std::fs::read_dir(data.join(dir))
                    .with_context(|| format!("failed to list {dir}"))?
                    .filter_map(|e| e.ok().map(|e| e.path()))
                    .filter(|p| p.extension().is_some_and(|e| e == "bin"))
                    .collect();
                found.sort();
                files.extend(found);
            }
            files.extend(kitti_heldout_files(data)?);
            files
        }
        other => bail!("--set {other}: give heldout or validation"),
    };
    let profile = SensorProfile::kitti_hdl64e().with_columns(512);
    files
        .iter()
        .map(|f| {
            let scan = lidar::kitti::read_bin(f)?;
            let image = lidar::project(&scan, &profile, Strategy::Auto)?;
            Ok((f.display().to_string(), image))
        })
        .collect()
}

/// Pixels of a hole of `kind` in `truth` (64 x 512), drawn with `rng`.
fn holes(kind: &str, truth: &RangeImage, rng: &mut Rng) -> Vec<bool> {
    let (h, w) = (truth.height, truth.width);
    let mut mask = vec![false; h * w];
    let mut patch = |rows: usize, cols: usize, count: usize, rng: &mut Rng| {
        for _ in 0..count {
            let (i0, j0) = (rng.below(h.saturating_sub(rows) + 1), rng.below(w));
            for i in i0..(i0 + rows).min(h) {
                for j in j0..j0 + cols {
                    mask[i * w + j % w] = true;
                }
            }
        }
    };
    // At 512 columns a column is 0.70 deg; rows are HDL-64E beams (~0.4 deg).
    match kind {
        "pixels" => {
            for m in mask.iter_mut() {
                *m = rng.below(20) == 0;
            }
        }
        "small" => patch(2, 2, 150, rng), // 2 beams x 1.5 deg
        "medium" => patch(6, 6, 40, rng), // 6 beams x 4 deg
        "large" => patch(16, 28, 8, rng), // 16 beams x 20 deg
        "beams" => {
            for _ in 0..4 {
                let i = rng.below(h);
                mask[i * w..(i + 1) * w].fill(true);
            }
        }
        "sector" => patch(h, 43, 1, rng), // 30 deg, every beam
        "objects" => objects(truth, rng, &mut mask),
        other => panic!("unknown kind {other}"),
    }
    mask
}

/// Object-shaped holes: connected surfaces (neighbouring returns within 3 % of each other's
/// range) within 25 m that stand in front of what is beside them, 30-600 pixels each, until
/// about 8 % of the returns are removed.
fn objects(truth: &RangeImage, rng: &mut Rng, mask: &mut [bool]) {
    let (h, w) = (truth.height, truth.width);
    let r = &truth.range_m;
    let target = truth.valid_count() / 12;
    let mut removed = 0;
    for _ in 0..400 {
        if removed >= target {
            break;
        }
        let seed = rng.below(h * w);
        if r[seed] <= 0.0 || r[seed] > 25.0 || mask[seed] {
            continue;
        }
        let mut region = vec![seed];
        let mut seen = std::collections::HashSet::from([seed]);
        let mut k = 0;
        let mut nearer_than_border = 0usize;
        let mut border = 0usize;
        while k < region.len() && region.len() < 600 {
            let p = region[k];
            k += 1;
            for q in lidar::holes::neighbours(p, h, w) {
                if seen.contains(&q) {
                    continue;
                }
                if r[q] > 0.0 && (r[q] - r[p]).abs() < 0.03 * r[p] {
                    seen.insert(q);
                    region.push(q);
                } else if r[q] > 0.0 {
                    border += 1;
                    nearer_than_border += usize::from(r[q] > r[p]);
                }
            }
        }
        let in_front = border > 0 && nearer_than_border * 2 > border;
        if (30..600).contains(&region.len()) && in_front {
            removed += region.len();
            for p in region {
                mask[p] = true;
            }
        }
    }
}

/// The returns of `image` outside `mask`, as a scan whose ring field is the row.
fn degraded_scan(image: &RangeImage, mask: &[bool]) -> Scan {
    let kept: Vec<usize> = (0..image.range_m.len())
        .filter(|&k| image.range_m[k] > 0.0 && !mask[k])
        .collect();
    let mut scan = Scan::from_xyz(kept.iter().map(|&k| image.xyz[k]).collect());
    scan.ring = Some(kept.iter().map(|&k| (k / image.width) as u16).collect());
    scan.intensity = Some(kept.iter().map(|&k| image.intensity[k]).collect());
    scan
}

/// The images of channel `suffix` in `path`, in log-time order.
fn images(path: &Path, suffix: &str) -> Result<Vec<Vec<f32>>> {
    let topic = format!("{TOPIC}/rangegan/{suffix}");
    let images = roundtrip::float_images(&std::fs::read(path)?, &topic)?;
    Ok(images.into_iter().map(|i| i.values).collect())
}

/// Each missing pixel of `observed` (0 = none) on a line between the nearest returns before
/// and after it along rows (`along_rows`, circular) or along columns; the one neighbour
/// where there is only one; 0 where the line holds no return.
fn interpolate(observed: &[f32], h: usize, w: usize, along_rows: bool) -> Vec<f32> {
    let mut out = observed.to_vec();
    let (lines, len) = if along_rows { (h, w) } else { (w, h) };
    let at = |line: usize, t: usize| {
        if along_rows {
            line * w + t
        } else {
            t * w + line
        }
    };
    for line in 0..lines {
        let hits: Vec<usize> = (0..len).filter(|&t| observed[at(line, t)] > 0.0).collect();
        if hits.is_empty() {
            continue;
        }
        for t in (0..len).filter(|&t| observed[at(line, t)] <= 0.0) {
            let after = hits.partition_point(|&x| x < t);
            let (before, next) = match (after.checked_sub(1), hits.get(after)) {
                (Some(b), Some(&n)) => (Some(hits[b] as isize), Some(n as isize)),
                (Some(b), None) if along_rows => {
                    (Some(hits[b] as isize), Some((hits[0] + len) as isize))
                }
                (None, Some(&n)) if along_rows => (
                    Some(hits[hits.len() - 1] as isize - len as isize),
                    Some(n as isize),
                ),
                (b, n) => (b.map(|b| hits[b] as isize), n.map(|&n| n as isize)),
            };
            let value = |x: isize| observed[at(line, x.rem_euclid(len as isize) as usize)];
            out[at(line, t)] = match (before, next) {
                (Some(a), Some(b)) => {
                    let f = (t as isize - a) as f32 / (b - a) as f32;
                    value(a) * (1.0 - f) + value(b) * f
                }
                (Some(a), None) => value(a),
                (None, Some(b)) => value(b),
                (None, None) => 0.0,
            };
        }
    }
    out
}

#[derive(Default)]
struct Score {
    pixels: usize,
    sums: BTreeMap<&'static str, f64>,
}

impl Score {
    fn add(&mut self, method: &'static str, error: f32) {
        *self.sums.entry(method).or_default() += error as f64;
    }
    fn mae(&self, method: &str) -> f64 {
        self.sums.get(method).copied().unwrap_or(f64::NAN) / self.pixels.max(1) as f64
    }
}

fn main() -> Result<()> {
    let mut data = PathBuf::from("../shared/real_lidar");
    let mut set = "heldout".to_string();
    let mut kinds: Vec<String> = KINDS.iter().map(|s| s.to_string()).collect();
    let mut convert_flags = Vec::new();
    let mut bin: Option<PathBuf> = None;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--data" => data = PathBuf::from(args.next().context("--data DIR")?),
            "--set" => set = args.next().context("--set NAME")?,
            "--bin" => bin = Some(PathBuf::from(args.next().context("--bin PATH")?)),
            "--kinds" => {
                kinds = (args.next().context("--kinds LIST")?)
                    .split(',')
                    .map(String::from)
                    .collect()
            }
            "--" => convert_flags.extend(args.by_ref()),
            other => bail!("unknown argument {other}"),
        }
    }
    if !data.exists() {
        eprintln!("skipped: {} not found", data.display());
        return Ok(());
    }
    let exe = std::env::current_exe()?;
    let bin = match bin {
        Some(b) => b,
        None => exe
            .parent()
            .and_then(Path::parent)
            .map(|d| d.join("rangegan-mcap"))
            .filter(|p| p.exists())
            .context("build the binary first: cargo build --release")?,
    };
    let scans = load(&data, &set)?;
    let dir = tempfile::tempdir()?;
    println!(
        "{} {set} scans; convert {}",
        scans.len(),
        convert_flags.join(" ")
    );
    println!(
        "| holes | pixels | `depth` | `x_d` | rows | columns | best interpolation | depth / best |"
    );
    println!("|---|---|---|---|---|---|---|---|");
    for kind in &kinds {
        let masks: Vec<Vec<bool>> = scans
            .iter()
            .enumerate()
            .map(|(s, (_, image))| {
                let seed = 0x5eed ^ ((s as u64) << 8) ^ (kind.len() as u64 * 0x9e37);
                holes(kind, image, &mut Rng(seed ^ kind.as_bytes()[0] as u64))
            })
            .collect();
        let degraded: Vec<Scan> = scans
            .iter()
            .zip(&masks)
            .map(|((_, image), mask)| degraded_scan(image, mask))
            .collect();
        let (input, output) = (dir.path().join("in.mcap"), dir.path().join("out.mcap"));
        roundtrip::write_scans(&input, TOPIC, "velodyne", &degraded)?;
        let status = std::process::Command::new(&bin)
            .args(["--quiet", "convert"])
            .arg(&input)
            .arg(&output)
            .args(["--sensor", "hdl64e", "--columns", "512", "--force"])
            .args(&convert_flags)
            .status()?;
        if !status.success() {
            bail!("convert failed on the {kind} holes");
        }
        let depth = images(&output, "depth")?;
        let x_d = images(&output, "x_d")?;
        let mut score = Score::default();
        for (s, (_, truth)) in scans.iter().enumerate() {
            let (h, w) = (truth.height, truth.width);
            let observed: Vec<f32> = (0..h * w)
                .map(|k| if masks[s][k] { 0.0 } else { truth.range_m[k] })
                .collect();
            let rows = interpolate(&observed, h, w, true);
            let cols = interpolate(&observed, h, w, false);
            for k in (0..h * w).filter(|&k| masks[s][k] && truth.range_m[k] > 0.0) {
                let t = truth.range_m[k];
                score.pixels += 1;
                score.add("rows", (rows[k] - t).abs());
                score.add("columns", (cols[k] - t).abs());
                if let Some(d) = depth.get(s) {
                    score.add("depth", (d[k] - t).abs());
                }
                if let Some(x) = x_d.get(s) {
                    score.add("x_d", (x[k] - t).abs());
                }
            }
        }
        let (r, c) = (score.mae("rows"), score.mae("columns"));
        let best = r.min(c);
        println!(
            "| {kind} | {} | {:.3} | {:.3} | {r:.3} | {c:.3} | {best:.3} ({}) | {:.2} |",
            score.pixels,
            score.mae("depth"),
            score.mae("x_d"),
            if r <= c { "rows" } else { "columns" },
            score.mae("depth") / best
        );
    }
    Ok(())
}
