//! Fits the learned hole fill ([`rangegan_mcap::decode::hole_fill`]) on KITTI training scans
//! with holes of every kind cut into them, converted by the built binary (`--upsample-method
//! guided`: the completion the network corrects, and x_d), and reports after
//! each epoch its MAE (m) against the completion it corrects, per kind of hole, on every
//! third scan of a drive left out of training. Writes `hole_fill.json` (copy it to `models/`
//! to ship it). Deterministic. Each kind of hole counts in the loss by its error relative to
//! the completion's. The decoded samples are kept beside it (`hole_fill_*.bin`) for reruns.
//! `--eval FILE` only reports a saved one.
//!
//! `--prior-free` fits the fill for sensors no model covers instead
//! (`hole_fill_prior_free.json`): the completion it corrects is the prior-free one, computed
//! here as `convert` computes it, its second opinion the line fill in place of x_d, and each
//! scan is put on a grid of its own (every beam, every second or every fourth; 512, 1024 or
//! 2048 columns, which the ~30 000 points of a KITTI training scan fill only in part) so
//! that it sees more than one spacing; validated on the three beam counts at 512 columns.
//!
//!     cargo build --release
//!     cargo run --release --example hole_fill_fit -- [--prior-free] [../shared/real_lidar]
//!         [per-scan pixels] [epochs] [hidden,hidden] [half rows] [half columns] [reach] [passes]
//!     cargo run --release --example hole_fill_fit -- --eval models/hole_fill.json [../shared/real_lidar]
use std::path::{Path, PathBuf};

use anyhow::Result;
use rangegan_mcap::decode::hole_fill::{HoleFill, Window};
use rangegan_mcap::decode::prior_free::prior_free_fills;
use rangegan_mcap::lidar::holes::HoleKind;
use rangegan_mcap::model::data::kitti_validation_split;
use rangegan_mcap::train::hole_fill::Holed;
use rangegan_mcap::train::ray_move::{Samples, TrainOptions, mae, train};
use rangegan_mcap::util::mlp::Mlp;
use rangegan_mcap::util::rng::{Rng, key_hash};
use rayon::prelude::*;

#[path = "common/holed.rs"]
mod holed;

/// Up to `per_scan` cut pixels with a true return from each of `files` (in order, one
/// recording), the `i`-th scan's holes of kind `kinds[i % kinds.len()]`, one set per kind;
/// every draw seeded from `seed` and the scan's position.
fn collect(
    window: Window,
    files: &[PathBuf],
    kinds: &[HoleKind],
    per_scan: usize,
    seed: u64,
) -> Result<Vec<Samples>> {
    let scans = holed::project_all(files, 512)?;
    let mut rngs: Vec<Rng> = (0..scans.len())
        .map(|i| Rng::new(key_hash(&[seed, i as u64])))
        .collect();
    let masks: Vec<Vec<bool>> = (scans.iter().zip(&mut rngs).enumerate())
        .map(|(i, (s, rng))| kinds[i % kinds.len()].cut(&s.range_m, s.height, s.width, rng))
        .collect();
    let degraded: Vec<_> = (scans.iter().zip(&masks))
        .map(|(s, m)| holed::degraded_scan(s, m))
        .collect();
    let dir = tempfile::tempdir()?;
    let flags = ["--upsample-method".to_string(), "guided".to_string()];
    let [completed, x_d]: [Vec<Vec<f32>>; 2] = holed::convert(
        &holed::kitti_grid(512),
        &holed::binary(None)?,
        dir.path(),
        &degraded,
        &flags,
        &["depth", "x_d"],
    )?
    .try_into()
    .expect("two channels");
    let mut sets: Vec<Samples> = kinds.iter().map(|_| Samples::default()).collect();
    for (i, (((truth, mask), (completed, x_d)), rng)) in (scans.iter().zip(masks))
        .zip(completed.into_iter().zip(x_d))
        .zip(&mut rngs)
        .enumerate()
    {
        let scan = Holed {
            height: truth.height,
            width: truth.width,
            observed: holed::observed(truth, &mask),
            completed,
            x_d,
            truth: truth.range_m.clone(),
            mask,
        };
        sets[i % kinds.len()].append(scan.samples(window, per_scan, rng));
    }
    Ok(sets)
}

/// The grids a prior-free sample is drawn on: every `step`-th beam of the HDL-64E, at
/// `columns`.
const PRIOR_FREE_GRIDS: [(usize, usize); 9] = [
    (1, 512),
    (1, 1024),
    (1, 2048),
    (2, 512),
    (2, 1024),
    (2, 2048),
    (4, 512),
    (4, 1024),
    (4, 2048),
];

/// As [`collect`] for the prior-free fill: the `i`-th scan on `grids[draw % grids.len()]`
/// and completed without a prior, in this process.
fn collect_prior_free(
    window: Window,
    files: &[PathBuf],
    kinds: &[HoleKind],
    grids: &[(usize, usize)],
    per_scan: usize,
    seed: u64,
) -> Result<Vec<Samples>> {
    let per_file: Vec<(usize, Samples)> = (files.par_iter().enumerate())
        .map(|(i, file)| {
            let mut rng = Rng::new(key_hash(&[seed, i as u64]));
            let (step, columns) = grids[rng.below(grids.len())];
            let scan = holed::project_all(std::slice::from_ref(file), columns)?.remove(0);
            let scan = holed::every_nth_row(&scan, step);
            let kind = i % kinds.len();
            let mask = kinds[kind].cut(&scan.range_m, scan.height, scan.width, &mut rng);
            let mut degraded = scan.clone();
            degraded.range_m = holed::observed(&scan, &mask);
            let (completed, lines) = prior_free_fills(&degraded);
            let holed = Holed {
                height: scan.height,
                width: scan.width,
                observed: degraded.range_m,
                completed,
                x_d: lines,
                truth: scan.range_m,
                mask,
            };
            Ok((kind, holed.samples(window, per_scan, &mut rng)))
        })
        .collect::<Result<_>>()?;
    let mut sets: Vec<Samples> = kinds.iter().map(|_| Samples::default()).collect();
    for (kind, s) in per_file {
        sets[kind].append(s);
    }
    Ok(sets)
}

fn list(s: &str) -> Vec<usize> {
    s.split(',').map(|v| v.parse().expect("a number")).collect()
}

/// Every cut pixel of every third scan of the validation drive, one set per kind of hole
/// (`prior_free`: each scan on each of the grids of [`PRIOR_FREE_GRIDS`] at 512 columns, as
/// `completion_eval --set thinned` puts them).
fn validation(window: Window, data: &Path, prior_free: bool) -> Result<Vec<Samples>> {
    let (_, files) = kitti_validation_split(data, &["kitti_raw_drive_d".to_string()])?;
    let files: Vec<PathBuf> = files.into_iter().step_by(3).collect();
    let grids: Vec<(usize, usize)> = PRIOR_FREE_GRIDS
        .into_iter()
        .filter(|g| g.1 == 512)
        .collect();
    HoleKind::ALL
        .iter()
        .map(|&kind| {
            if !prior_free {
                return Ok(collect(window, &files, &[kind], usize::MAX, 0)?.remove(0));
            }
            let mut set = Samples::default();
            for g in &grids {
                let one = collect_prior_free(window, &files, &[kind], &[*g], usize::MAX, 0)?;
                set.append(one.into_iter().next().expect("one kind"));
            }
            Ok(set)
        })
        .collect()
}

/// `sets` as raw little-endian numbers, so that a fit can be rerun without decoding again.
fn save(path: &Path, sets: &[Samples]) -> Result<()> {
    let mut out = Vec::new();
    out.extend((sets.len() as u64).to_le_bytes());
    for s in sets {
        out.extend((s.features as u64).to_le_bytes());
        out.extend((s.len() as u64).to_le_bytes());
        for v in [&s.x, &s.reference, &s.truth, &s.weight] {
            out.extend(v.iter().flat_map(|f| f.to_le_bytes()));
        }
    }
    Ok(std::fs::write(path, out)?)
}

fn load(path: &Path) -> Result<Vec<Samples>> {
    let bytes = std::fs::read(path)?;
    let mut at = 0;
    let word = |at: &mut usize| {
        let v = u64::from_le_bytes(bytes[*at..*at + 8].try_into().unwrap()) as usize;
        *at += 8;
        v
    };
    let floats = |at: &mut usize, len: usize| -> Vec<f32> {
        let v = bytes[*at..*at + 4 * len]
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
            .collect();
        *at += 4 * len;
        v
    };
    let count = word(&mut at);
    let mut sets = Vec::new();
    for _ in 0..count {
        let (features, n) = (word(&mut at), word(&mut at));
        sets.push(Samples {
            features,
            x: floats(&mut at, n * features),
            reference: floats(&mut at, n),
            truth: floats(&mut at, n),
            weight: floats(&mut at, n),
        });
    }
    Ok(sets)
}

/// The sets in `cache` if it is there, else `make`'s, saved there.
fn cached(cache: &Path, make: impl FnOnce() -> Result<Vec<Samples>>) -> Result<Vec<Samples>> {
    if cache.exists() {
        return load(cache);
    }
    let sets = make()?;
    save(cache, &sets)?;
    Ok(sets)
}

fn report(sets: &[Samples], net: &Mlp) -> String {
    HoleKind::ALL
        .iter()
        .zip(sets)
        .map(|(kind, set)| {
            let m = mae(set, net);
            let n = set.len();
            format!(
                "{} ({n}) {:.3} -> {:.3}",
                kind.name(),
                m.fill[0],
                m.corrected[0]
            )
        })
        .collect::<Vec<_>>()
        .join(" | ")
}

fn main() -> Result<()> {
    let mut args = std::env::args().skip(1).peekable();
    let prior_free = args.next_if(|a| a == "--prior-free").is_some();
    if args.peek().is_some_and(|a| a == "--eval") {
        args.next();
        let fill = HoleFill::load(Path::new(&args.next().expect("--eval FILE")))?;
        let data = PathBuf::from(args.next().unwrap_or("../shared/real_lidar".into()));
        let sets = validation(fill.window, &data, prior_free)?;
        println!("{}", report(&sets, &fill.net));
        return Ok(());
    }
    let data = PathBuf::from(args.next().unwrap_or("../shared/real_lidar".into()));
    let per_scan: usize = args.next().map_or(2000, |s| s.parse().unwrap());
    let epochs: usize = args.next().map_or(20, |s| s.parse().unwrap());
    let hidden = args.next().map_or(vec![64, 64], |s| list(&s));
    let window = Window {
        half_rows: args.next().map_or(2, |s| s.parse().unwrap()),
        half_columns: args.next().map_or(2, |s| s.parse().unwrap()),
        reach: args.next().map_or(32, |s| s.parse().unwrap()),
    };
    let passes: usize = args.next().map_or(2, |s| s.parse().unwrap());
    let (train_files, _) = kitti_validation_split(&data, &["kitti_raw_drive_d".to_string()])?;
    let files: Vec<PathBuf> = (0..passes).flat_map(|_| train_files.clone()).collect();
    let t = std::time::Instant::now();
    let name = if prior_free {
        "hole_fill_prior_free"
    } else {
        "hole_fill"
    };
    let tag = format!(
        "{per_scan}-{}-{}-{}-{passes}",
        window.half_rows, window.half_columns, window.reach
    );
    let training = cached(Path::new(&format!("{name}_training-{tag}.bin")), || {
        if prior_free {
            collect_prior_free(
                window,
                &files,
                &HoleKind::ALL,
                &PRIOR_FREE_GRIDS,
                per_scan,
                7,
            )
        } else {
            collect(window, &files, &HoleKind::ALL, per_scan, 7)
        }
    })?;
    let samples = Samples::balanced(training);
    let sets = cached(Path::new(&format!("{name}_validation-{tag}.bin")), || {
        validation(window, &data, prior_free)
    })?;
    eprintln!(
        "{} training scans x {passes}, {} samples ({:.0} s)",
        train_files.len(),
        samples.len(),
        t.elapsed().as_secs_f64()
    );
    let opts = TrainOptions {
        epochs,
        hidden,
        ..TrainOptions::default()
    };
    let net = train(&samples, &opts, |epoch, loss, net| {
        let secs = t.elapsed().as_secs_f64();
        eprintln!(
            "epoch {epoch} loss {loss:.3} ({secs:.0} s) | {}",
            report(&sets, net)
        );
    });
    let fill = HoleFill::new(window, net);
    std::fs::write(format!("{name}.json"), serde_json::to_string(&fill)?)?;
    Ok(())
}
