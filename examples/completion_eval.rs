//! Completion of dropped rays as users get it from `convert`: held-out KITTI scans with holes
//! of several kinds cut into them (single pixels; small, medium and large patches; whole
//! beams; an azimuth sector; object-shaped holes), converted by the built binary, and the
//! `depth` and `x_d` channels scored on every hole pixel whose truth has a return, beside
//! interpolating the degraded scan along its rows, along its columns, and the better of the
//! two per kind of hole.
//!
//!     cargo build --release
//!     cargo run --release --example completion_eval -- [--data ../shared/real_lidar]
//!         [--set heldout|validation|full-resolution] [--columns 512] [--kinds pixels,...]
//!         [--bin BINARY]
//!         [--against 'FLAGS'|none] [-- CONVERT FLAGS...]
//!
//! `validation` (every third scan of the validation drive) is where settings are chosen;
//! `heldout` (the 26 held-out scans) is where they are reported; `full-resolution` is its six
//! full-resolution scans, for `--columns 2048` (hole sizes scale with the columns). Flags after `--` go to
//! `convert` (e.g. `--upsample-method gan` for the decoded scene alone in the holes);
//! `--against` scores a second convert beside it, side by side (by default
//! `--upsample-method guided`, the completion without the learned hole fill).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use rangegan_mcap::lidar::RangeImage;
use rangegan_mcap::lidar::holes::HoleKind;
use rangegan_mcap::model::data::{kitti_heldout_files, kitti_validation_split};
use rangegan_mcap::util::rng::{Rng, key_hash};

#[path = "common/holed.rs"]
mod holed;

/// The scans of `set`, projected onto the HDL-64E grid at `columns`.
fn load(data: &Path, set: &str, columns: usize) -> Result<Vec<RangeImage>> {
    let files: Vec<PathBuf> = match set {
        "validation" => {
            let (_, files) = kitti_validation_split(data, &["kitti_raw_drive_d".to_string()])?;
            files.into_iter().step_by(3).collect()
        }
        "heldout" | "full-resolution" => {
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
            if set == "heldout" {
                files.extend(kitti_heldout_files(data)?);
            }
            files
        }
        other => bail!("--set {other}: give heldout or validation"),
    };
    holed::project_all(&files, columns)
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
    let mut columns = 512;
    let mut kinds = HoleKind::ALL.to_vec();
    let mut convert_flags = Vec::new();
    let mut bin: Option<PathBuf> = None;
    let mut against: Option<Vec<String>> = Some(vec!["--upsample-method".into(), "guided".into()]);
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--data" => data = PathBuf::from(args.next().context("--data DIR")?),
            "--set" => set = args.next().context("--set NAME")?,
            "--columns" => columns = args.next().context("--columns N")?.parse()?,
            "--bin" => bin = Some(PathBuf::from(args.next().context("--bin PATH")?)),
            "--kinds" => {
                kinds = (args.next().context("--kinds LIST")?)
                    .split(',')
                    .map(|k| HoleKind::parse(k).with_context(|| format!("no hole kind {k}")))
                    .collect::<Result<_>>()?
            }
            "--against" => {
                let flags = args.next().context("--against 'FLAGS' (or none)")?;
                against =
                    (flags != "none").then(|| flags.split_whitespace().map(String::from).collect());
            }
            "--" => convert_flags.extend(args.by_ref()),
            other => bail!("unknown argument {other}"),
        }
    }
    if !data.exists() {
        eprintln!("skipped: {} not found", data.display());
        return Ok(());
    }
    let bin = holed::binary(bin)?;
    let scans = load(&data, &set, columns)?;
    let dir = tempfile::tempdir()?;
    println!(
        "{} {set} scans; convert {}",
        scans.len(),
        convert_flags.join(" ")
    );
    let against_name = against.as_ref().map_or("-".into(), |a| a.join(" "));
    println!(
        "| holes | pixels | `depth` | {against_name} | `x_d` | rows | columns | best interpolation | depth / best |"
    );
    println!("|---|---|---|---|---|---|---|---|---|");
    for kind in kinds {
        let masks: Vec<Vec<bool>> = scans
            .iter()
            .enumerate()
            .map(|(s, image)| {
                let mut rng = Rng::new(key_hash(&[0x5eed, s as u64, kind as u64]));
                kind.cut(&image.range_m, image.height, image.width, &mut rng)
            })
            .collect();
        let degraded: Vec<_> = (scans.iter().zip(&masks))
            .map(|(image, mask)| holed::degraded_scan(image, mask))
            .collect();
        let against = match &against {
            Some(flags) => Some(holed::convert(
                columns,
                &bin,
                dir.path(),
                &degraded,
                flags,
                &["depth"],
            )?),
            None => None,
        }
        .map(|mut a| a.remove(0));
        let [depth, x_d]: [Vec<Vec<f32>>; 2] = holed::convert(
            columns,
            &bin,
            dir.path(),
            &degraded,
            &convert_flags,
            &["depth", "x_d"],
        )?
        .try_into()
        .expect("two channels");
        let mut score = Score::default();
        for (s, truth) in scans.iter().enumerate() {
            let (h, w) = (truth.height, truth.width);
            let observed = holed::observed(truth, &masks[s]);
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
                if let Some(d) = against.as_ref().and_then(|a| a.get(s)) {
                    score.add("against", (d[k] - t).abs());
                }
                if let Some(x) = x_d.get(s) {
                    score.add("x_d", (x[k] - t).abs());
                }
            }
        }
        let (r, c) = (score.mae("rows"), score.mae("columns"));
        let best = r.min(c);
        println!(
            "| {} | {} | {:.3} | {:.3} | {:.3} | {r:.3} | {c:.3} | {best:.3} ({}) | {:.2} |",
            kind.name(),
            score.pixels,
            score.mae("depth"),
            score.mae("against"),
            score.mae("x_d"),
            if r <= c { "rows" } else { "columns" },
            score.mae("depth") / best
        );
    }
    Ok(())
}
