//! Fits the learned row fill on KITTI training scans and reports its MAE against the
//! edge-aware fill on every third scan of a drive left out of training.
//!
//!     cargo run --release --example row_fill_fit -- [../shared/real_lidar] [per-scan pixels] [epochs] [hidden,hidden] [beams per side] [half columns]
use std::path::PathBuf;

use anyhow::Result;
use rangegan_mcap::decode::row_fill::{RowFill, Window};
use rangegan_mcap::model::data::kitti_validation_split;
use rangegan_mcap::train::row_fill::{TrainOptions, collect, mae, train};

fn main() -> Result<()> {
    let mut args = std::env::args().skip(1);
    let data = PathBuf::from(args.next().unwrap_or("../shared/real_lidar".into()));
    let per_scan: usize = args.next().map_or(1500, |s| s.parse().unwrap());
    let epochs: usize = args.next().map_or(4, |s| s.parse().unwrap());
    let hidden: Vec<usize> = args.next().map_or(vec![64, 64], |s| {
        s.split(',').map(|v| v.parse().unwrap()).collect()
    });
    let window = Window {
        beams_per_side: args.next().map_or(2, |s| s.parse().unwrap()),
        half_columns: args.next().map_or(2, |s| s.parse().unwrap()),
    };
    let (train_files, val_files) =
        kitti_validation_split(&data, &["kitti_raw_drive_d".to_string()])?;
    let val_files: Vec<PathBuf> = val_files.into_iter().step_by(3).collect();
    let t = std::time::Instant::now();
    let samples = collect(window, &train_files, &[8, 16], per_scan, 7)?;
    let val16 = collect(window, &val_files, &[16], usize::MAX, 0)?;
    let val8 = collect(window, &val_files, &[8], usize::MAX, 0)?;
    eprintln!(
        "{} training scans, {} samples; validation {} scans, {} / {} pixels ({:.0} s)",
        train_files.len(),
        samples.len(),
        val_files.len(),
        val16.len(),
        val8.len(),
        t.elapsed().as_secs_f64()
    );
    let opts = TrainOptions {
        epochs,
        hidden,
        ..TrainOptions::default()
    };
    let fill = train(&samples, &opts, |epoch, loss, fill| {
        let (a, b) = (mae(&val16, fill), mae(&val8, fill));
        eprintln!(
            "epoch {epoch} loss {loss:.3} ({:.0} s) | 16 lines fill {:.3} {:.3} {:.3} -> {:.3} {:.3} {:.3} | 8 lines {:.3} {:.3} {:.3} -> {:.3} {:.3} {:.3}",
            t.elapsed().as_secs_f64(),
            a.fill[0],
            a.fill[1],
            a.fill[2],
            a.corrected[0],
            a.corrected[1],
            a.corrected[2],
            b.fill[0],
            b.fill[1],
            b.fill[2],
            b.corrected[0],
            b.corrected[1],
            b.corrected[2],
        );
    });
    let fill = RowFill::new(window, fill);
    std::fs::write("row_fill.json", serde_json::to_string(&fill)?)?;
    Ok(())
}
