//! What `convert` writes for real recordings of several makes, judged on each sensor's own
//! pixels: KITTI's HDL-64E (the validation drive, SemanticKITTI 00, full resolution), a real OS1-64
//! recording, an HDL-32E-like pair, nuScenes' HDL-32E, an indoor VLP-16, a Hesai XT32 and a
//! VLS-128 (from `../shared/real_lidar`). Per recording:
//!
//! - the grid of `depth` against the grid of `range` (the sensor's): its rows and columns,
//!   and the share of the sensor's returns that land on a row of `depth` at all;
//! - `depth` at the returns: relative L1 against `range`;
//! - `raydrop_prob`: NLL per pixel of each scan's actual drops, beside the per-row drop rate
//!   of the recording's other scans (of the scan itself where a recording has one scan), the
//!   recording's own per-pixel rates (`DropCensus`) and products of `raydrop_prob` with them
//!   at three weights (how the weight `convert` uses was chosen, on the validation drive).
//!
//! With `--old BINARY` the same rows for another build, side by side. A build whose outputs
//! lie on another grid than the sensor's is scored where its pixels are: each of the sensor's
//! pixels takes the output pixel of its direction (nearest row within half a row's spacing,
//! column by azimuth), and pixels no output row reaches count as missing.
//!
//!     cargo build --release
//!     cargo run --release --example sensor_eval -- [--data ../shared/real_lidar] [--old BIN]
//!         [-- CONVERT FLAGS...]

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use rangegan_mcap::io::decoders::{CloudFormat, decode_cloud};
use rangegan_mcap::io::roundtrip::{self, FloatImage as Image};
use rangegan_mcap::lidar::drop_census::{
    DropCensus, combine_with_rates, pixel_nll, row_rates as row_rates_of,
};
use rangegan_mcap::lidar::projection::ring_order_ids;
use rangegan_mcap::lidar::{Scan, estimate_profile, kitti, nuscenes, pcd};

const TOPIC: &str = "/points";

/// A recording to judge: a name and the MCAP holding it, with the topic to read.
struct Case {
    name: String,
    mcap: PathBuf,
    topic: String,
    /// The recording's first scan (the sensor's profile is estimated from it).
    first: Scan,
}

/// The float images of `topic` in `path`, in log-time order.
fn images(path: &Path, topic: &str) -> Result<Vec<Image>> {
    roundtrip::float_images(&std::fs::read(path)?, topic)
}

fn sorted_files(dir: &Path, suffix: &str) -> Result<Vec<PathBuf>> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("failed to list {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.to_string_lossy().ends_with(suffix))
        .collect();
    files.sort();
    Ok(files)
}

/// The recordings found under `data`, written to MCAP in `dir` where they are not MCAP.
fn cases(data: &Path, dir: &Path) -> Result<Vec<Case>> {
    let mut out = Vec::new();
    let mut add = |name: &str, scans: Vec<Scan>| -> Result<()> {
        if scans.is_empty() {
            return Ok(());
        }
        let mcap = dir.join(format!("{name}.mcap"));
        roundtrip::write_scans(&mcap, TOPIC, "lidar", &scans)?;
        out.push(Case {
            name: format!("{name} ({} scans)", scans.len()),
            mcap,
            topic: TOPIC.into(),
            first: scans[0].clone(),
        });
        Ok(())
    };
    let read_all = |files: Vec<PathBuf>, read: &dyn Fn(&Path) -> Result<Scan>| {
        files.iter().map(|f| read(f)).collect::<Result<Vec<_>>>()
    };
    // With the ring field `rangegan-mcap import` gives KITTI scans.
    let kitti_bin = |p: &Path| {
        let mut scan = kitti::read_bin(p)?;
        let rings = ring_order_ids(&scan)
            .into_iter()
            .map(|r| r.min(u16::MAX as u32) as u16);
        scan.ring = Some(rings.collect());
        Ok(scan)
    };
    let pcd_file = |p: &Path| Ok(pcd::read_pcd(p)?);
    let val = sorted_files(&data.join("kitti_raw_drive_d"), ".bin")?;
    add(
        "KITTI HDL-64E, validation drive d",
        read_all(val, &kitti_bin)?,
    )?;
    let sk = data.join("semantickitti_mini/00/velodyne");
    add(
        "KITTI HDL-64E, SemanticKITTI 00",
        read_all(sorted_files(&sk, ".bin")?, &kitti_bin)?,
    )?;
    let full = sorted_files(&data.join("semantickitti_ssv3"), ".bin")?;
    add("KITTI HDL-64E full resolution", read_all(full, &kitti_bin)?)?;
    let hdl32 = sorted_files(&data.join("other_sensors/fast_gicp_hdl32e"), ".pcd")?;
    add("HDL-32E-like pair", read_all(hdl32, &pcd_file)?)?;
    let nus = sorted_files(&data.join("nuscenes"), ".pcd.bin")?;
    add(
        "nuScenes HDL-32E",
        read_all(nus, &|p: &Path| Ok(nuscenes::read_bin(p)?))?,
    )?;
    add(
        "VLP-16 indoors",
        read_all(sorted_files(&data.join("nebula"), ".pcd")?, &pcd_file)?,
    )?;
    let xt32 = sorted_files(&data.join("other_sensors/nebula_hesai_xt32"), ".pcd")?;
    add("Hesai XT32", read_all(xt32, &pcd_file)?)?;
    let vls = sorted_files(&data.join("other_sensors/nebula_velodyne_vls128"), ".pcd")?;
    add("Velodyne VLS-128", read_all(vls, &pcd_file)?)?;
    let ouster = data.join("mcap/pointcloudset_test.mcap");
    if ouster.exists() {
        let topic = "/os1_cloud_node/points";
        let bytes = std::fs::read(&ouster)?;
        let mut first = None;
        for m in mcap::MessageStream::new(&bytes)? {
            let m = m?;
            let schema = m
                .channel
                .schema
                .as_ref()
                .map(|s| s.name.as_str())
                .unwrap_or("");
            let format = CloudFormat::detect(&m.channel.message_encoding, schema);
            if let (true, Some(format), None) = (m.channel.topic == topic, format, &first) {
                first = Some(decode_cloud(format, &m.data)?.scan);
            }
        }
        out.push(Case {
            name: "Ouster OS1-64 gen 1 (2 scans, MCAP)".into(),
            mcap: ouster,
            topic: topic.into(),
            first: first.context("no cloud in the Ouster recording")?,
        });
    }
    Ok(out)
}

/// Scores of one build on one recording.
#[derive(Default)]
struct Score {
    grid: String,
    /// The sensor's returns and those on a row of `depth`.
    returns: usize,
    reached: usize,
    rel_l1: f64,
    nll: f64,
    nll_rows: f64,
    /// The recording's own per-pixel rates, fitted on its other scans (`DropCensus`).
    nll_census: f64,
    /// x_n and the recording's rates as a product of experts, per weight of x_n in [`BLENDS`].
    nll_blend: [f64; BLENDS.len()],
    /// Pixels scored for NLL.
    scored: usize,
}

/// Where each pixel of `sensor` (rows at `elevations`, degrees, top first; columns by
/// azimuth as `convert` lays them) lies on an `h x w` output of the same recording: the same
/// pixel where the grids agree, else on the model grid (the only other grid `convert` has
/// written `depth` on), the nearest model row within half its spacing.
fn mapping(sensor: (usize, usize), out: (usize, usize), elevations: &[f32]) -> Vec<Option<usize>> {
    let (sh, sw) = sensor;
    let (h, w) = out;
    if (sh, sw) == (h, w) {
        return (0..sh * sw).map(Some).collect();
    }
    let model = rangegan_mcap::decode::model_grid().resized(h, w);
    let rows: Vec<f32> = model
        .row_elevations()
        .iter()
        .map(|e| e.to_degrees())
        .collect();
    (0..sh * sw)
        .map(|k| {
            let (r, c) = (k / sw, k % sw);
            let e = *elevations.get(r)?;
            let (i, d) = (rows.iter().enumerate())
                .map(|(i, m)| (i, (m - e).abs()))
                .min_by(|a, b| a.1.total_cmp(&b.1))?;
            let n = if i + 1 < rows.len() {
                i + 1
            } else {
                i.checked_sub(1)?
            };
            if d > 0.5 * (rows[i] - rows[n]).abs() {
                return None;
            }
            let col = (c as f64 * w as f64 / sw as f64).round() as usize % w;
            Some(i * w + col)
        })
        .collect()
}

/// Weights of x_n against the recording's rates tried in the product of experts.
const BLENDS: [f32; 3] = [0.15, 0.25, 0.35];

/// Per-row drop rates of `range[s]`'s recording without scan `s` (the scan's own where the
/// recording has one scan).
fn row_rates(range: &[Image], s: usize) -> Vec<f64> {
    let (h, w) = (range[s].height, range[s].width);
    let others: Vec<&Image> = match range.len() {
        1 => vec![&range[0]],
        _ => (0..range.len())
            .filter(|&i| i != s)
            .map(|i| &range[i])
            .collect(),
    };
    (0..h)
        .map(|r| {
            let dropped: usize = (others.iter())
                .map(|img| {
                    img.values[r * w..(r + 1) * w]
                        .iter()
                        .filter(|&&d| d <= 0.0)
                        .count()
                })
                .sum();
            (dropped as f64 + 1.0) / ((others.len() * w) as f64 + 2.0)
        })
        .collect()
}

/// The recording's own drop rates for scan `s`, fitted on its other scans (the scan's own
/// per-row rate where it has none).
fn census_rates(range: &[Image], s: usize) -> Vec<f32> {
    let (h, w) = (range[s].height, range[s].width);
    let as_image = |img: &Image| {
        let grid = rangegan_mcap::lidar::AngleGrid::regular_columns(h, w, |_| 0.0);
        let mut r = rangegan_mcap::lidar::RangeImage::empty(grid);
        r.range_m = img.values.clone();
        r
    };
    let mut census = DropCensus::new(h, w);
    for img in range {
        census.add(&as_image(img));
    }
    let own = as_image(&range[s]);
    census
        .rates_for(&own, true)
        .unwrap_or_else(|| row_rates_of(&own))
}

fn score(range: &[Image], depth: &[Image], drop: &[Image], elevations: &[f32]) -> Score {
    let mut sc = Score::default();
    let (mut l1, mut n_l1) = (0.0f64, 0usize);
    if let Some(d) = depth.first() {
        sc.grid = format!("{} x {}", d.height, d.width);
    }
    for (s, img) in range.iter().enumerate() {
        let (Some(d), Some(p)) = (depth.get(s), drop.get(s)) else {
            continue;
        };
        let map = mapping((img.height, img.width), (d.height, d.width), elevations);
        let rows = row_rates(range, s);
        let census = census_rates(range, s);
        for (k, &t) in img.values.iter().enumerate() {
            let dropped = t <= 0.0;
            sc.returns += usize::from(!dropped);
            let Some(o) = map[k] else { continue };
            sc.reached += usize::from(!dropped);
            if !dropped && d.values[o] > 0.0 {
                l1 += ((d.values[o] - t).abs() / t) as f64;
                n_l1 += 1;
            }
            sc.nll += pixel_nll(p.values[o], dropped);
            sc.nll_rows += pixel_nll(rows[k / img.width] as f32, dropped);
            sc.nll_census += pixel_nll(census[k], dropped);
            for (b, wt) in BLENDS.iter().enumerate() {
                let mut combined = [p.values[o]];
                combine_with_rates(&mut combined, &census[k..=k], *wt);
                sc.nll_blend[b] += pixel_nll(combined[0], dropped);
            }
            sc.scored += 1;
        }
    }
    sc.rel_l1 = l1 / n_l1.max(1) as f64;
    sc.nll /= sc.scored.max(1) as f64;
    sc.nll_rows /= sc.scored.max(1) as f64;
    sc.nll_census /= sc.scored.max(1) as f64;
    for b in &mut sc.nll_blend {
        *b /= sc.scored.max(1) as f64;
    }
    sc
}

/// Converts `case` with `bin` and scores its outputs against the sensor's `range` images.
fn run(
    bin: &Path,
    case: &Case,
    dir: &Path,
    flags: &[String],
    range: &[Image],
    elevations: &[f32],
) -> Result<Score> {
    let out = dir.join("out.mcap");
    let status = std::process::Command::new(bin)
        .args(["--quiet", "convert"])
        .arg(&case.mcap)
        .arg(&out)
        .args(["--force", "--topic", &case.topic])
        .args(flags)
        .status()?;
    if !status.success() {
        bail!("{}: convert failed on {}", bin.display(), case.name);
    }
    let ch = |s: &str| images(&out, &format!("{}/rangegan/{s}", case.topic));
    let (depth, drop) = (ch("depth")?, ch("raydrop_prob")?);
    Ok(score(range, &depth, &drop, elevations))
}

fn main() -> Result<()> {
    let mut data = PathBuf::from("../shared/real_lidar");
    let mut old: Option<PathBuf> = None;
    let mut flags = Vec::new();
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--data" => data = PathBuf::from(args.next().context("--data DIR")?),
            "--old" => old = Some(PathBuf::from(args.next().context("--old BINARY")?)),
            "--" => flags.extend(args.by_ref()),
            other => bail!("unknown argument {other}"),
        }
    }
    if !data.exists() {
        eprintln!("skipped: {} not found", data.display());
        return Ok(());
    }
    let exe = std::env::current_exe()?;
    let bin = (exe.parent().and_then(Path::parent))
        .map(|d| d.join("rangegan-mcap"))
        .filter(|p| p.exists())
        .context("build the binary first: cargo build --release")?;
    let dir = tempfile::tempdir()?;
    let cases = cases(&data, dir.path())?;
    println!(
        "| recording | build | `depth` grid (range grid) | returns on a row | depth rel. L1 at returns | x_n NLL | per-row rate NLL | recording's rates NLL | products at weights {BLENDS:?} | x_n / per-row |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|");
    for case in &cases {
        let range = images_of(&bin, case, dir.path(), &flags)?;
        if range.is_empty() {
            bail!("{}: no range images", case.name);
        }
        let elevations = sensor_row_elevations(case)?;
        let builds: Vec<(&str, &Path)> = std::iter::once(("this", bin.as_path()))
            .chain(old.as_deref().map(|o| ("old", o)))
            .collect();
        for (label, b) in builds {
            let sc = run(b, case, dir.path(), &flags, &range, &elevations)?;
            println!(
                "| {} | {label} | {} ({} x {}) | {:.1} % | {:.4} | {:.4} | {:.4} | {:.4} | {:.4} / {:.4} / {:.4} | {:.2} |",
                case.name,
                sc.grid,
                range[0].height,
                range[0].width,
                100.0 * sc.reached as f64 / sc.returns.max(1) as f64,
                sc.rel_l1,
                sc.nll,
                sc.nll_rows,
                sc.nll_census,
                sc.nll_blend[0],
                sc.nll_blend[1],
                sc.nll_blend[2],
                sc.nll / sc.nll_rows
            );
        }
    }
    Ok(())
}

/// The flags of `flags` that choose the grid (`--sensor`, `--columns`), with their values.
fn grid_flags(flags: &[String]) -> Vec<String> {
    let mut out = Vec::new();
    let mut it = flags.iter();
    while let Some(f) = it.next() {
        if f == "--sensor" || f == "--columns" {
            out.push(f.clone());
            out.extend(it.next().cloned());
        } else if f.starts_with("--sensor=") || f.starts_with("--columns=") {
            out.push(f.clone());
        }
    }
    out
}

/// The `range` images of `case` (the sensor's grid), from a `--quality off` conversion.
fn images_of(bin: &Path, case: &Case, dir: &Path, flags: &[String]) -> Result<Vec<Image>> {
    let out = dir.join("range.mcap");
    let status = std::process::Command::new(bin)
        .args(["--quiet", "convert", "--quality", "off"])
        .arg(&case.mcap)
        .arg(&out)
        .args(["--force", "--topic", &case.topic])
        .args(grid_flags(flags))
        .status()?;
    if !status.success() {
        bail!("convert --quality off failed on {}", case.name);
    }
    images(&out, &format!("{}/rangegan/range", case.topic))
}

/// The elevation of each row of the sensor's grid (degrees, top first): the profile
/// `convert --sensor auto` estimates from the recording's first scan.
fn sensor_row_elevations(case: &Case) -> Result<Vec<f32>> {
    let profile = estimate_profile(std::slice::from_ref(&case.first))?.profile;
    let grid = profile.with_columns(16).angle_grid();
    Ok(grid
        .row_elevations()
        .iter()
        .map(|e| e.to_degrees())
        .collect())
}
