//! Completion of dropped rays as users get it from `convert`: held-out KITTI scans with holes
//! of several kinds cut into them (single pixels; small, medium and large patches; whole
//! beams; an azimuth sector; object-shaped holes), converted by the built binary, and the
//! `depth` and `x_d` channels scored on every hole pixel whose truth has a return, beside
//! interpolating the degraded scan along its rows, along its columns, and the better of the
//! two per kind of hole.
//!
//!     cargo build --release
//!     cargo run --release --example completion_eval -- [--data ../shared/real_lidar]
//!         [--set heldout|validation|thinned|full-resolution|sensors] [--columns 512]
//!         [--kinds pixels,...]
//!         [--bin BINARY]
//!         [--against 'FLAGS'|none] [-- CONVERT FLAGS...]
//!
//! `validation` (every third scan of the validation drive) is where settings are chosen;
//! `thinned` is the same scans with every beam, every second and every fourth kept (64, 32
//! and 16 beams): with `-- --prior-free`, where the completion without a prior is chosen;
//! `heldout` (the 26 held-out scans) is where they are reported; `full-resolution` is its six
//! full-resolution scans, for `--columns 2048` (hole sizes scale with the columns); `sensors` is
//! each real recording of another sensor (Ouster, Velodyne, Hesai, nuScenes) on its own grid,
//! one table each. Flags after `--` go to
//! `convert` (e.g. `--upsample-method gan` for the decoded scene alone in the holes);
//! `--against` scores a second convert beside it, side by side (by default
//! `--upsample-method guided`, the completion without the learned hole fill; with
//! `-- --prior-free`, give it `--against '--prior-free --upsample-method guided'` for the
//! completion without the prior-free hole fill).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use rangegan_mcap::lidar::holes::HoleKind;
use rangegan_mcap::lidar::{RangeImage, SensorProfile};
use rangegan_mcap::model::data::{kitti_heldout_files, kitti_validation_split};
use rangegan_mcap::recording::{self, Grid};
use rangegan_mcap::util::rng::{Rng, key_hash};

#[path = "common/holed.rs"]
mod holed;

/// Scans of one sensor and the `convert` flags that put them on its grid.
struct Recorded {
    name: String,
    scans: Vec<RangeImage>,
    grid: Vec<String>,
}

/// The real recordings of sensors other than KITTI's HDL-64E: a name, and a recording or
/// what `import` reads (relative to `--data`).
const SENSORS: [(&str, &str); 8] = [
    ("Ouster OS1-32", "ouster/OS-1-32-G_v2.1.1_1024x10.pcap"),
    ("Ouster OS1-64", "mcap/pointcloudset_test.mcap"),
    (
        "Ouster OS1-128",
        "other_sensors/ouster_os1_128_lb_3frames/OS-1-128_v2.3.0_1024x10_lb_n3.pcap",
    ),
    ("Velodyne VLP-16", "nebula"),
    ("HDL-32E (fast_gicp)", "other_sensors/fast_gicp_hdl32e"),
    ("nuScenes 32-beam", "nuscenes"),
    ("Hesai PandarXT32", "other_sensors/nebula_hesai_xt32"),
    ("Velodyne VLS-128", "other_sensors/nebula_velodyne_vls128"),
];

/// The scans of `set`: KITTI's on the HDL-64E grid at `columns`, or (`sensors`) each real
/// recording of another sensor on its own grid, as `convert` finds it.
fn load(data: &Path, set: &str, columns: usize, bin: &Path, dir: &Path) -> Result<Vec<Recorded>> {
    let files: Vec<PathBuf> = match set {
        "thinned" => {
            let (_, files) = kitti_validation_split(data, &["kitti_raw_drive_d".to_string()])?;
            let files: Vec<PathBuf> = files.into_iter().step_by(3).collect();
            let scans = holed::project_all(&files, columns)?;
            return [1, 2, 4]
                .iter()
                .map(|&step| thinned(&scans, step, columns, dir))
                .collect();
        }
        "sensors" => {
            return SENSORS
                .iter()
                .map(|(n, f)| sensor(data, n, f, bin, dir))
                .collect();
        }
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
        other => {
            bail!("--set {other}: give heldout, validation, thinned, full-resolution or sensors")
        }
    };
    Ok(vec![Recorded {
        name: format!("KITTI HDL-64E, {set}, {columns} columns"),
        scans: holed::project_all(&files, columns)?,
        grid: holed::kitti_grid(columns),
    }])
}

/// `scans` (on the HDL-64E grid at `columns`) with every `step`-th beam kept, and the profile
/// of that sensor, written for `convert`.
fn thinned(scans: &[RangeImage], step: usize, columns: usize, dir: &Path) -> Result<Recorded> {
    let mut profile = SensorProfile::kitti_hdl64e().with_columns(columns);
    profile.elevation_deg = profile.elevation_deg.into_iter().step_by(step).collect();
    profile.name = format!("HDL-64E, every {step} beams");
    let path = dir.join(format!("thinned_{step}.profile.json"));
    std::fs::write(&path, serde_json::to_string(&profile)?)?;
    Ok(Recorded {
        name: format!(
            "KITTI validation drive, {} beams of 64, {} scan(s)",
            profile.elevation_deg.len(),
            scans.len()
        ),
        scans: scans
            .iter()
            .map(|s| holed::every_nth_row(s, step))
            .collect(),
        grid: vec!["--sensor".into(), path.display().to_string()],
    })
}

/// The real recording `source` of sensor `name`, imported by `bin` where it is not an MCAP,
/// read on the grid `convert` estimates for it; that grid is written as a profile file, so
/// the scans with holes cut into them are converted on the same grid.
fn sensor(data: &Path, name: &str, source: &str, bin: &Path, dir: &Path) -> Result<Recorded> {
    let source = data.join(source);
    let slug: String = (name.chars())
        .map(|c| if c.is_ascii_alphanumeric() { c } else { '_' })
        .collect();
    let mcap = if source.extension().is_some_and(|e| e == "mcap") {
        source
    } else {
        let out = dir.join(format!("{slug}.mcap"));
        let status = std::process::Command::new(bin)
            .args(["--quiet", "import"])
            .arg(&source)
            .arg(&out)
            .arg("--force")
            .status()?;
        if !status.success() {
            bail!("import {} failed", source.display());
        }
        out
    };
    let recording = recording::read(&mcap, None, &Grid::FromRecording { columns: None })?;
    let profile = dir.join(format!("{slug}.profile.json"));
    std::fs::write(&profile, serde_json::to_string(&recording.profile)?)?;
    Ok(Recorded {
        name: format!(
            "{name}, {} scan(s) of {} x {}",
            recording.images.len(),
            recording.profile.beams(),
            recording.profile.columns
        ),
        scans: recording.images,
        grid: vec!["--sensor".into(), profile.display().to_string()],
    })
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
    let dir = tempfile::tempdir()?;
    for recorded in load(&data, &set, columns, &bin, dir.path())? {
        println!("\n{}; convert {}", recorded.name, convert_flags.join(" "));
        score_recording(
            &recorded,
            &kinds,
            &bin,
            dir.path(),
            &convert_flags,
            &against,
        )?;
    }
    Ok(())
}

/// The table of `recorded` with holes of each of `kinds` cut into its scans.
fn score_recording(
    recorded: &Recorded,
    kinds: &[HoleKind],
    bin: &Path,
    dir: &Path,
    convert_flags: &[String],
    against: &Option<Vec<String>>,
) -> Result<()> {
    let scans = &recorded.scans;
    let against_name = against.as_ref().map_or("-".into(), |a| a.join(" "));
    println!(
        "| holes | pixels | `depth` | {against_name} | `x_d` | rows | columns | best interpolation | depth / best |"
    );
    println!("|---|---|---|---|---|---|---|---|---|");
    for &kind in kinds {
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
        let against = match against {
            Some(flags) => Some(holed::convert(
                &recorded.grid,
                bin,
                dir,
                &degraded,
                flags,
                &["depth"],
            )?),
            None => None,
        }
        .map(|mut a| a.remove(0));
        let [depth, x_d]: [Vec<Vec<f32>>; 2] = holed::convert(
            &recorded.grid,
            bin,
            dir,
            &degraded,
            convert_flags,
            &["depth", "x_d"],
        )?
        .try_into()
        .expect("two channels");
        let mut score = Score::default();
        for (s, truth) in scans.iter().enumerate() {
            let (h, w) = (truth.height, truth.width);
            let observed = holed::observed(truth, &masks[s]);
            let rows = holed::interpolate(&observed, h, w, true);
            let cols = holed::interpolate(&observed, h, w, false);

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
