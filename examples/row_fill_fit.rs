//! Fits the learned row fill ([`rangegan_mcap::decode::row_fill`]) on KITTI training scans
//! and reports, after each epoch, its MAE against the edge-aware fill (all / near / far) on
//! every third scan of a drive left out of training, for 4, 8, 16 and 32 kept lines. Writes
//! `row_fill.json` (copy it to `models/` to ship it). Deterministic. `--eval FILE` only
//! reports a saved one.
//!
//!     cargo run --release --example row_fill_fit -- [../shared/real_lidar] [per-scan pixels]
//!         [epochs] [hidden,hidden] [beams per side] [half columns] [training lines,..]
//!     cargo run --release --example row_fill_fit -- --eval models/row_fill.json [../shared/real_lidar]
use std::path::{Path, PathBuf};

use anyhow::Result;
use rangegan_mcap::decode::row_fill::{RowFill, Window};
use rangegan_mcap::model::data::kitti_validation_split;
use rangegan_mcap::train::ray_move::{Samples, TrainOptions, mae, train};
use rangegan_mcap::train::row_fill::collect;
use rangegan_mcap::util::mlp::Mlp;

const VALIDATION_LINES: [usize; 4] = [4, 8, 16, 32];

fn list(s: &str) -> Vec<usize> {
    s.split(',').map(|v| v.parse().expect("a number")).collect()
}

fn validation(window: Window, data: &Path) -> Result<Vec<Samples>> {
    let (_, files) = kitti_validation_split(data, &["kitti_raw_drive_d".to_string()])?;
    let files: Vec<PathBuf> = files.into_iter().step_by(3).collect();
    VALIDATION_LINES
        .iter()
        .map(|&n| collect(window, &files, &[n], usize::MAX, 0))
        .collect()
}

fn report(sets: &[Samples], net: &Mlp) -> String {
    VALIDATION_LINES
        .iter()
        .zip(sets)
        .map(|(n, set)| {
            let m = mae(set, net);
            let [a, b, c] = m.fill;
            let [x, y, z] = m.corrected;
            format!("{n} lines {a:.3} {b:.3} {c:.3} -> {x:.3} {y:.3} {z:.3}")
        })
        .collect::<Vec<_>>()
        .join(" | ")
}

fn main() -> Result<()> {
    let mut args = std::env::args().skip(1).peekable();
    if args.peek().is_some_and(|a| a == "--eval") {
        args.next();
        let fill = RowFill::load(Path::new(&args.next().expect("--eval FILE")))?;
        let data = PathBuf::from(args.next().unwrap_or("../shared/real_lidar".into()));
        println!("{}", report(&validation(fill.window, &data)?, &fill.net));
        return Ok(());
    }
    let data = PathBuf::from(args.next().unwrap_or("../shared/real_lidar".into()));
    let per_scan: usize = args.next().map_or(4000, |s| s.parse().unwrap());
    let epochs: usize = args.next().map_or(3, |s| s.parse().unwrap());
    let hidden = args.next().map_or(vec![64, 64], |s| list(&s));
    let window = Window {
        beams_per_side: args.next().map_or(2, |s| s.parse().unwrap()),
        half_columns: args.next().map_or(2, |s| s.parse().unwrap()),
    };
    let lines = args.next().map_or(vec![8, 16], |s| list(&s));
    let (train_files, _) = kitti_validation_split(&data, &["kitti_raw_drive_d".to_string()])?;
    let t = std::time::Instant::now();
    let samples = collect(window, &train_files, &lines, per_scan, 7)?;
    let sets = validation(window, &data)?;
    eprintln!(
        "{} training scans, {} samples from {lines:?} kept lines ({:.0} s)",
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
    let fill = RowFill::new(window, net);
    std::fs::write("row_fill.json", serde_json::to_string(&fill)?)?;
    Ok(())
}
