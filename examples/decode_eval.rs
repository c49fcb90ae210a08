//! The auto-decoding numbers on held-out real KITTI scans (none used in training): reconstruction
//! error of `fast` and `paper`, upsampling (16 -> 64 beams, 512 -> 2048 columns), restoration
//! (8 of 64 lines, 10 % of points) against nearest / bilinear interpolation, and ray-drop
//! calibration. Prints a JSON report (and Markdown tables on stderr).
//!
//!     cargo run --release --example decode_eval -- --data ../shared/real_lidar \
//!         [--paper-scans 2] [--fast-scans 26] [--encoder DIR] [--model DIR] [--out eval.json]
//!         [--png docs/img/raydrop_reliability.png] [--sparse-paper-scans 4] [--only-sparse]
//!         [--tune N] [--validation kitti_raw_drive_d] [--fast-schedule ...] [--only-reconstruction]
//!         [--only-raydrop]
//!         [--reference-scans 4]
//!
//! The upsampling and restoration cases also measure the library's fills that `convert
//! --upsample-method` offers (guided, edge-aware), with MAE near (<= 30 m) and far and the
//! share of pixels more than 1 m off. `--tune N` measures a grid of surface rules on N
//! KITTI TRAINING scans (never the held-out ones) and stops; `--only-sparse` runs only the
//! upsampling and restoration cases. `--validation DRIVE` measures on every third scan of a
//! KITTI drive set aside from training instead, for choosing settings without the held-out
//! scans.
//!
//! Held out: `semantickitti_mini/00`, `/07` (every 4th point, ~512 per ring) and the
//! full-resolution `semantickitti_ssv3`, `patchworkpp` (~2010 per ring; ground truth for the
//! 512 -> 2048 column test). Scans are decoded in parallel (rayon over scans, one thread each).

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use rangegan_mcap::decode::amortised::TrainedEncoder;
use rangegan_mcap::decode::{
    DecodeOptions, Decoded, Decoder, Fill, Quality, Schedule, Sparsify, model_grid,
};
use rangegan_mcap::lidar::{
    self, AngleGrid, Interpolation, RangeImage, SensorProfile, Strategy, SurfaceRule,
    resample_image,
};
use rangegan_mcap::model::calibration::bernoulli_nll;
use rangegan_mcap::model::data::{MAX_DEPTH_M, MIN_DEPTH_M, kitti_training_files};
use rangegan_mcap::model::weights::Model;
use rayon::prelude::*;
use serde_json::json;

struct Args {
    data: PathBuf,
    paper_scans: usize,
    fast_scans: usize,
    encoder: Option<PathBuf>,
    model: Option<PathBuf>,
    out: Option<PathBuf>,
    /// `w_steps,w_lr,tune_steps,tune_lr,tune_decay,tune_w_lr[,coarse_steps]` of the fast path
    /// (default: `Schedule::fast()`); coarse steps `..:quarter:half` (coarsest first) bring the full-resolution
    /// steps' rate decay to 0.
    fast_schedule: Option<Schedule>,
    /// Stop after the reconstruction numbers (for tuning the fast schedule).
    only_reconstruction: bool,
    only_raydrop: bool,
    /// Write the ray-drop reliability curves here (PNG).
    png: Option<PathBuf>,
    /// Also run the row upsampling / restoration cases with `paper` decodes on this many scans.
    sparse_paper_scans: usize,
    /// Also decode this many scans with the paper's own schedule from w_avg (`Schedule::reference`).
    reference_scans: usize,
    /// Only the upsampling and restoration cases (skip reconstruction and calibration).
    only_sparse: bool,
    /// Tune the surface rule of the guided and edge-aware fills on this many TRAINING scans
    /// (never the held-out ones) and stop.
    tune: Option<usize>,
    /// Measure on every third scan of this folder of `--data` instead of the held-out scans:
    /// a drive left out of training, for choosing settings without the held-out scans.
    validation: Option<String>,
}

fn parse_args() -> Result<Args> {
    let mut a = Args {
        data: PathBuf::from("../shared/real_lidar"),
        paper_scans: 2,
        fast_scans: usize::MAX,
        encoder: None,
        model: None,
        out: None,
        fast_schedule: None,
        only_reconstruction: false,
        only_raydrop: false,
        png: None,
        sparse_paper_scans: 0,
        reference_scans: 0,
        only_sparse: false,
        validation: None,
        tune: None,
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let mut value = || it.next().with_context(|| format!("{flag} needs a value"));
        match flag.as_str() {
            "--data" => a.data = PathBuf::from(value()?),
            "--paper-scans" => a.paper_scans = value()?.parse()?,
            "--fast-scans" => a.fast_scans = value()?.parse()?,
            "--encoder" => a.encoder = Some(PathBuf::from(value()?)),
            "--model" => a.model = Some(PathBuf::from(value()?)),
            "--out" => a.out = Some(PathBuf::from(value()?)),
            "--png" => a.png = Some(PathBuf::from(value()?)),
            "--sparse-paper-scans" => a.sparse_paper_scans = value()?.parse()?,
            "--reference-scans" => a.reference_scans = value()?.parse()?,
            "--only-reconstruction" => a.only_reconstruction = true,
            "--only-raydrop" => a.only_raydrop = true,
            "--only-sparse" => a.only_sparse = true,
            "--validation" => a.validation = Some(value()?),
            "--tune" => a.tune = Some(value()?.parse()?),
            "--fast-schedule" => {
                let v = value()?;
                let p: Vec<&str> = v.split(',').collect();
                if p.len() != 6 && p.len() != 7 {
                    bail!(
                        "--fast-schedule w_steps,w_lr,tune_steps,tune_lr,tune_decay(0|1),tune_w_lr[,coarse_steps[:coarser..]]"
                    );
                }
                let coarse_steps: Vec<usize> = p
                    .get(6)
                    .map(|c| c.split(':').map(str::parse).collect::<Result<_, _>>())
                    .transpose()?
                    .unwrap_or_default();
                a.fast_schedule = Some(Schedule {
                    w_steps: p[0].parse()?,
                    w_lr: p[1].parse()?,
                    tune_steps: p[2].parse()?,
                    tune_lr: p[3].parse()?,
                    tune_decay: p[4] == "1",
                    tune_w_lr: p[5].parse()?,
                    pyramid_levels: 2,
                    coarse_steps,
                    ..Schedule::fast()
                });
            }
            other => bail!("unknown flag {other}"),
        }
    }
    Ok(a)
}

/// One held-out scan: its 64 x 512 projection and, for full-resolution scans, 64 x 2048.
struct Scan {
    name: String,
    image: RangeImage,
    full: Option<RangeImage>,
}

fn valid_range(img: &mut RangeImage) {
    for r in &mut img.range_m {
        if !(MIN_DEPTH_M..=MAX_DEPTH_M).contains(r) {
            *r = 0.0;
        }
    }
}

/// Projects `path` onto 64 x 512 and, with `full`, 64 x 2048 (kept only when the scan is
/// full resolution: more than twice the 512-column returns).
fn load_scan(data: &Path, path: &Path, full: bool) -> Result<Scan> {
    let p512 = SensorProfile::kitti_hdl64e().with_columns(512);
    let p2048 = SensorProfile::kitti_hdl64e().with_columns(2048);
    let scan = lidar::kitti::read_bin(path)?;
    let mut image = lidar::project(&scan, &p512, Strategy::Auto)?;
    valid_range(&mut image);
    let full = if full {
        let mut f = lidar::project(&scan, &p2048, Strategy::Auto)?;
        valid_range(&mut f);
        (f.valid_count() > 2 * image.valid_count()).then_some(f)
    } else {
        None
    };
    let name = path
        .strip_prefix(data)
        .unwrap_or(path)
        .display()
        .to_string();
    Ok(Scan { name, image, full })
}

fn load_scans(data: &Path, validation: Option<&str>) -> Result<Vec<Scan>> {
    if let Some(dir) = validation {
        let (_, files) =
            rangegan_mcap::model::data::kitti_validation_split(data, &[dir.to_string()])?;
        return files
            .iter()
            .step_by(3)
            .map(|f| load_scan(data, f, true))
            .collect();
    }
    let mut out = Vec::new();
    for dir in ["semantickitti_ssv3", "patchworkpp"] {
        let mut files: Vec<PathBuf> = std::fs::read_dir(data.join(dir))
            .with_context(|| format!("failed to list {dir}"))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|e| e == "bin"))
            .collect();
        files.sort();
        for f in files {
            out.push(load_scan(data, &f, true)?);
        }
    }
    for f in rangegan_mcap::model::data::kitti_heldout_files(data)? {
        out.push(load_scan(data, &f, false)?);
    }
    Ok(out)
}

/// `n` training scans spread evenly over the training files (for tuning only).
fn load_training_scans(data: &Path, n: usize) -> Result<Vec<Scan>> {
    let files = kitti_training_files(data)?;
    let step = (files.len() / n.max(1)).max(1);
    files
        .iter()
        .step_by(step)
        .take(n)
        .map(|f| load_scan(data, f, true))
        .collect()
}

/// The interpolation baselines of the upsampling and row-restoration tasks, in order.
/// The baselines of the row cases: the grid ones with per-column linear interpolation.
const LINE_BASELINES: [&str; 6] = [
    "gan_fast",
    "nearest",
    "bilinear",
    "column_linear",
    "anchored_add",
    "anchored_mul",
];

const GRID_BASELINES: [&str; 5] = [
    "gan_fast",
    "nearest",
    "bilinear",
    "anchored_add",
    "anchored_mul",
];

/// A library fill measured beside the baselines: `convert --upsample-method NAME` with `rule`.
struct Variant {
    name: String,
    fill: Fill,
    rule: SurfaceRule,
}

/// The library fills measured by default: the ones `convert` offers, with the shipped rule.
fn default_variants() -> Vec<Variant> {
    [Fill::Learned, Fill::Guided, Fill::EdgeAware]
        .into_iter()
        .map(|fill| Variant {
            name: fill.name().replace('-', "_"),
            fill,
            rule: SurfaceRule::default(),
        })
        .chain(std::iter::once(Variant {
            // Where the gain comes from: plain bilinear (IDW), but in inverse depth.
            name: "bilinear_inverse_depth".into(),
            fill: Fill::EdgeAware,
            rule: SurfaceRule {
                inverse_depth: true,
                ..SurfaceRule::ANY
            },
        }))
        .collect()
}

/// Truth at or below this is "near".
const NEAR_M: f32 = 30.0;

/// Error sums of one method on one scan.
#[derive(Debug, Clone, Copy, Default)]
struct ErrorSums {
    near: f64,
    near_n: usize,
    far: f64,
    far_n: usize,
    /// Pixels more than 1 m off the true surface.
    off_1m: usize,
    /// Pixels the method left empty, scored with the fallback.
    holes: usize,
}

impl ErrorSums {
    fn add(&mut self, o: &ErrorSums) {
        self.near += o.near;
        self.near_n += o.near_n;
        self.far += o.far;
        self.far_n += o.far_n;
        self.off_1m += o.off_1m;
        self.holes += o.holes;
    }

    fn n(&self) -> usize {
        self.near_n + self.far_n
    }

    fn mae(&self) -> f64 {
        (self.near + self.far) / self.n().max(1) as f64
    }
}

/// Absolute errors in meters over every pixel where `truth` is measured and `mask` allows,
/// split near (truth <= 30 m) / far. Each prediction comes with its fallback: where the
/// method leaves a pixel empty it is scored with what its user gets there (`convert`'s
/// fills: x_d; an interpolation baseline: the nearest return), never skipped; a pixel
/// nothing answers counts as a prediction of 0 m.
fn errors(
    truth: &[f32],
    preds: &[(&[f32], &[f32])],
    mask: &dyn Fn(usize) -> bool,
) -> Vec<ErrorSums> {
    let mut sums = vec![ErrorSums::default(); preds.len()];
    for k in 0..truth.len() {
        if truth[k] <= 0.0 || !mask(k) {
            continue;
        }
        let near = truth[k] <= NEAR_M;
        for (s, (p, fallback)) in sums.iter_mut().zip(preds) {
            let hole = p[k] <= 0.0;
            let value = if hole { fallback[k].max(0.0) } else { p[k] };
            let e = f64::from((value - truth[k]).abs());
            if near {
                s.near += e;
                s.near_n += 1;
            } else {
                s.far += e;
                s.far_n += 1;
            }
            s.off_1m += usize::from(e > 1.0);
            s.holes += usize::from(hole);
        }
    }
    sums
}

/// The predictions of a case with their fallbacks: the interpolation baselines fall back to
/// the nearest return (`nearest`), `convert`'s fills to the rendering x_d (`x_d`), as
/// `convert` completes them.
fn with_fallbacks<'a>(
    baselines: &[&'a Vec<f32>],
    nearest: &'a [f32],
    fills: &'a [Vec<f32>],
    x_d: &'a [f32],
) -> Vec<(&'a [f32], &'a [f32])> {
    baselines
        .iter()
        .map(|b| (b.as_slice(), nearest))
        .chain(fills.iter().map(|f| (f.as_slice(), x_d)))
        .collect()
}

/// For every pixel of an `h x w` image of observed ranges (0 = none), the nearest observed
/// range in its column, else in its row (circular): the fallback a user has for a hole.
fn nearest_in_column_then_row(observed: &[f32], h: usize, w: usize) -> Vec<f32> {
    let mut out = vec![0f32; h * w];
    for c in 0..w {
        let rows: Vec<usize> = (0..h).filter(|r| observed[r * w + c] > 0.0).collect();
        if rows.is_empty() {
            continue;
        }
        for r in 0..h {
            let nearest = rows
                .iter()
                .min_by_key(|&&q| q.abs_diff(r))
                .expect("not empty");
            out[r * w + c] = observed[nearest * w + c];
        }
    }
    for r in 0..h {
        let row = &observed[r * w..(r + 1) * w];
        let cols: Vec<usize> = (0..w).filter(|&c| row[c] > 0.0).collect();
        for c in 0..w {
            if out[r * w + c] > 0.0 || cols.is_empty() {
                continue;
            }
            let gap = |q: usize| q.abs_diff(c).min(w - q.abs_diff(c));
            let nearest = cols.iter().min_by_key(|&&q| gap(q)).expect("not empty");
            out[r * w + c] = row[*nearest];
        }
    }
    out
}

/// Per-column linear interpolation of range, in elevation angle, between the nearest
/// observed returns above and below each pixel; one side only: that side's range; none: 0.
fn column_linear(observed: &[f32], elevation_rad: &[f32], h: usize, w: usize) -> Vec<f32> {
    let mut out = vec![0f32; h * w];
    for c in 0..w {
        let rows: Vec<usize> = (0..h).filter(|r| observed[r * w + c] > 0.0).collect();
        for r in 0..h {
            let k = r * w + c;
            let above = rows.iter().rev().find(|&&q| q <= r);
            let below = rows.iter().find(|&&q| q >= r);
            out[k] = match (above, below) {
                (Some(&a), Some(&b)) if a == b => observed[a * w + c],
                (Some(&a), Some(&b)) => {
                    let (ea, eb, e) = (
                        elevation_rad[a * w + c],
                        elevation_rad[b * w + c],
                        elevation_rad[k],
                    );
                    let t = if (eb - ea).abs() > 1e-9 {
                        ((e - ea) / (eb - ea)).clamp(0.0, 1.0)
                    } else {
                        0.5
                    };
                    observed[a * w + c] * (1.0 - t) + observed[b * w + c] * t
                }
                (Some(&q), None) | (None, Some(&q)) => observed[q * w + c],
                (None, None) => 0.0,
            };
        }
    }
    out
}

/// The kept rows of `img` as their own image (with their angles), for row interpolation.
fn rows_image(img: &RangeImage, rows: &[usize]) -> RangeImage {
    let w = img.width;
    let grid = AngleGrid {
        height: rows.len(),
        width: w,
        elevation_rad: rows
            .iter()
            .flat_map(|r| img.angles.elevation_rad[r * w..(r + 1) * w].to_vec())
            .collect(),
        azimuth_rad: rows
            .iter()
            .flat_map(|r| img.angles.azimuth_rad[r * w..(r + 1) * w].to_vec())
            .collect(),
    };
    let mut out = RangeImage::empty(grid);
    for (i, r) in rows.iter().enumerate() {
        for j in 0..w {
            out.range_m[i * w + j] = img.range_m[r * w + j];
            let [x, y, z] = img.angles.direction(r * w + j);
            let d = img.range_m[r * w + j];
            out.xyz[i * w + j] = [x * d, y * d, z * d];
        }
    }
    out
}

/// Scattered-point baselines on the image grid: nearest observed pixel and inverse-distance
/// weighting of the observed pixels within twice the nearest distance (search radius 8 px).
fn scattered_baselines(observed: &[f32], h: usize, w: usize) -> (Vec<f32>, Vec<f32>) {
    let mut nearest = vec![0.0; h * w];
    let mut idw = vec![0.0; h * w];
    let r = 8isize;
    for i in 0..h as isize {
        for j in 0..w as isize {
            let mut found: Vec<(f32, f32)> = Vec::new();
            for di in -r..=r {
                let ii = i + di;
                if ii < 0 || ii >= h as isize {
                    continue;
                }
                for dj in -r..=r {
                    let jj = (j + dj).rem_euclid(w as isize);
                    let v = observed[ii as usize * w + jj as usize];
                    if v > 0.0 {
                        found.push((((di * di + dj * dj) as f32).sqrt(), v));
                    }
                }
            }
            let Some(&(d0, v0)) = found.iter().min_by(|a, b| a.0.total_cmp(&b.0)) else {
                continue;
            };
            let k = i as usize * w + j as usize;
            nearest[k] = v0;
            let (mut s, mut ws) = (0.0, 0.0);
            for (d, v) in &found {
                if *d <= 2.0 * d0.max(0.5) {
                    let wt = 1.0 / d.max(0.5);
                    s += wt * v;
                    ws += wt;
                }
            }
            idw[k] = s / ws;
        }
    }
    (nearest, idw)
}

/// Residual anchoring: the GAN rendering corrected by the interpolated residual of the
/// observation (`base_obs` = an interpolation of the observation, `base_gan` = the same
/// interpolation of the GAN's values at the observed pixels). Additive and multiplicative.
fn anchored(gan: &[f32], base_obs: &[f32], base_gan: &[f32]) -> (Vec<f32>, Vec<f32>) {
    let f = |mult: bool| -> Vec<f32> {
        gan.iter()
            .zip(base_obs.iter().zip(base_gan))
            .map(|(g, (o, b))| {
                if *g <= 0.0 || *o <= 0.0 || *b <= 0.0 {
                    *g
                } else if mult {
                    g * o / b
                } else {
                    (g + o - b).max(0.5)
                }
            })
            .collect()
    };
    (f(false), f(true))
}

/// `values` where `like` has a return, else 0 (same validity as the observation).
fn with_validity_of(like: &RangeImage, values: &[f32]) -> RangeImage {
    let mut out = like.clone();
    for (k, r) in out.range_m.iter_mut().enumerate() {
        if *r > 0.0 {
            *r = values[k];
        }
    }
    out
}

fn decoder(
    model: &Option<PathBuf>,
    encoder: &Option<PathBuf>,
    mut opts: DecodeOptions,
    fast_schedule: &Option<Schedule>,
) -> Result<Decoder> {
    let dev = burn::tensor::Device::flex();
    if let (Some(s), Quality::Fast) = (fast_schedule, opts.quality) {
        let keep_off = opts.schedule.steps() == 0;
        opts.schedule = s.clone();
        if keep_off {
            opts.schedule.w_steps = 0;
            opts.schedule.tune_steps = 0;
        }
    }
    let mut d = Decoder::new(Model::load(model.as_deref(), &dev)?, opts)?;
    if let Some(e) = encoder {
        d = d.with_encoder(TrainedEncoder::from_dir(e, &dev)?)?;
    }
    Ok(d)
}

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len().max(1) as f64
}

fn main() -> Result<()> {
    rangegan_mcap::model::tune_allocator(); // as the binary does
    let args = parse_args()?;
    if !args.data.exists() {
        eprintln!("skipped: {} not found", args.data.display());
        return Ok(());
    }
    let scans = load_scans(&args.data, args.validation.as_deref())?;
    let fast_n = args.fast_scans.min(scans.len());
    let paper_n = args.paper_scans.min(scans.len());
    eprintln!(
        "{} held-out scans ({} fast, {} paper)",
        scans.len(),
        fast_n,
        paper_n
    );
    let model_source = Model::load(args.model.as_deref(), &burn::tensor::Device::flex())?.source;
    let fast = decoder(
        &args.model,
        &args.encoder,
        DecodeOptions::new(Quality::Fast),
        &args.fast_schedule,
    )?;
    if let Some(n) = args.tune {
        return tune(&args, &fast, n);
    }
    let header = json!({
        "model": model_source,
        "encoder": args.encoder.as_ref().map_or("shipped".to_string(), |p| p.display().to_string()),
        "scans": scans.iter().map(|s| s.name.clone()).collect::<Vec<_>>(),
    });
    if args.only_sparse {
        let sparse = sparse_cases(&args, &fast, &scans[..fast_n], &default_variants())?;
        return write_report(&args, header, json!({"upsampling_and_restoration": sparse}));
    }
    let paper = decoder(
        &args.model,
        &args.encoder,
        DecodeOptions::new(Quality::Paper),
        &None,
    )?;
    let mut reference_opts = DecodeOptions::new(Quality::Paper);
    reference_opts.schedule = Schedule::reference();
    let reference = decoder(&args.model, &None, reference_opts, &None)?.without_encoder();
    let mut no_enc_opts = DecodeOptions::new(Quality::Paper);
    no_enc_opts.schedule = args.fast_schedule.clone().unwrap_or_else(Schedule::fast);
    let no_encoder = decoder(&args.model, &None, no_enc_opts, &None)?.without_encoder();
    let mut encoder_only_opts = DecodeOptions::new(Quality::Fast);
    encoder_only_opts.schedule.w_steps = 0;
    encoder_only_opts.schedule.tune_steps = 0;
    let encoder_only = decoder(&args.model, &args.encoder, encoder_only_opts, &None)?;

    // ---- Reconstruction ----------------------------------------------------------------
    // Per-scan times include waiting for a free worker; throughput is scans / wall time.
    let timed = |d: &Decoder, s: &Scan, seed: u64| -> Result<(Decoded, f64)> {
        let t = Instant::now();
        let r = d.decode(&s.image, seed)?;
        Ok((r, t.elapsed().as_secs_f64()))
    };
    let t0 = Instant::now();
    let fast_res: Vec<(Decoded, f64)> = scans[..fast_n]
        .par_iter()
        .enumerate()
        .map(|(i, s)| timed(&fast, s, i as u64))
        .collect::<Result<_>>()?;
    let fast_wall = t0.elapsed().as_secs_f64();
    let ablation: Vec<(f64, f64)> = scans[..fast_n]
        .par_iter()
        .enumerate()
        .map(|(i, s)| -> Result<(f64, f64)> {
            let a = encoder_only
                .decode(&s.image, i as u64)?
                .error
                .unwrap_or(f32::NAN);
            let b = no_encoder
                .decode(&s.image, i as u64)?
                .error
                .unwrap_or(f32::NAN);
            Ok((f64::from(a), f64::from(b)))
        })
        .collect::<Result<_>>()?;
    let decode_all = |d: &Decoder, n: usize| -> Result<(Vec<(Decoded, f64)>, f64)> {
        let t = Instant::now();
        let res = scans[..n]
            .par_iter()
            .enumerate()
            .map(|(i, s)| timed(d, s, i as u64))
            .collect::<Result<_>>()?;
        Ok((res, t.elapsed().as_secs_f64()))
    };
    let (paper_res, paper_wall) = decode_all(&paper, paper_n)?;
    let reference_n = args.reference_scans.min(scans.len());
    let (reference_res, reference_wall) = decode_all(&reference, reference_n)?;
    let err = |r: &[(Decoded, f64)]| -> Vec<f64> {
        r.iter()
            .map(|(d, _)| f64::from(d.error.unwrap_or(f32::NAN)))
            .collect()
    };
    let fast_err = err(&fast_res);
    let paper_err = err(&paper_res);
    let reference_err = err(&reference_res);
    let fast_on_paper_scans = mean(&fast_err[..paper_n.min(fast_n)]);
    let speedup = (fast_n as f64 / fast_wall) / (paper_n as f64 / paper_wall);
    let reconstruction = json!({
        "threads": rayon::current_num_threads(),
        "fast_speedup_over_paper": speedup,
        "fast": {"scans": fast_n, "rel_l1_mean": mean(&fast_err), "rel_l1_per_scan": fast_err,
                  "scans_per_sec": fast_n as f64 / fast_wall, "wall_secs": fast_wall,
                  "steps": fast.options().schedule.steps()},
        "fast_on_paper_scans": fast_on_paper_scans,
        "paper": {"scans": paper_n, "rel_l1_mean": mean(&paper_err), "rel_l1_per_scan": paper_err,
                   "scans_per_sec": paper_n as f64 / paper_wall, "wall_secs": paper_wall,
                   "steps": paper.options().schedule.steps()},
        "reference": {"scans": reference_n, "rel_l1_mean": mean(&reference_err),
                      "rel_l1_per_scan": reference_err,
                      "scans_per_sec": reference_n as f64 / reference_wall,
                      "steps": reference.options().schedule.steps()},
        "encoder_only_rel_l1": mean(&ablation.iter().map(|a| a.0).collect::<Vec<_>>()),
        "w_avg_plus_fast_steps_rel_l1": mean(&ablation.iter().map(|a| a.1).collect::<Vec<_>>()),
    });
    eprintln!("reconstruction: {reconstruction}");
    if args.only_reconstruction {
        println!("{}", serde_json::to_string_pretty(&reconstruction)?);
        return Ok(());
    }

    // ---- Ray-drop calibration (fast decodes of the full scans) ---------------------------
    let (mut rel, mut rel_raw) = (Reliability::new(10), Reliability::new(10));
    let (mut nll, mut nll_raw, mut n_pix) = (0.0f64, 0.0f64, 0usize);
    let mut rows_drop = vec![(0.0f64, 0usize); 64];
    for (s, (d, _)) in scans[..fast_n].iter().zip(&fast_res) {
        let (_, raw_logits) = d.depth_and_keep_logits(&fast);
        for (k, raw) in raw_logits.iter().enumerate() {
            let dropped = s.image.range_m[k] <= 0.0;
            let p = f64::from(d.model.drop_prob[k]).clamp(1e-4, 1.0 - 1e-4);
            nll -= if dropped { p.ln() } else { (1.0 - p).ln() };
            nll_raw += bernoulli_nll(f64::from(*raw), !dropped);
            n_pix += 1;
            rel.add(p, dropped);
            rel_raw.add(1.0 / (1.0 + f64::from(*raw).exp()), dropped);
            let row = k / s.image.width;
            rows_drop[row].0 += f64::from(u8::from(dropped));
            rows_drop[row].1 += 1;
        }
    }
    // Baselines from the training scans: one global drop rate and one per row.
    let train = rangegan_mcap::model::data::RangeDataset::from_kitti_files(
        &kitti_training_files(&args.data)?,
        512,
    )?;
    let mut row_rate = vec![(0.0f64, 0.0f64); 64];
    for i in 0..train.len() {
        for (k, v) in train.image(i).iter().enumerate() {
            let row = k / 512;
            row_rate[row].0 += f64::from(u8::from(*v <= -1.0));
            row_rate[row].1 += 1.0;
        }
    }
    let global =
        row_rate.iter().map(|r| r.0).sum::<f64>() / row_rate.iter().map(|r| r.1).sum::<f64>();
    let (mut nll_global, mut nll_row) = (0.0f64, 0.0f64);
    for s in &scans[..fast_n] {
        for k in 0..s.image.len() {
            let dropped = s.image.range_m[k] <= 0.0;
            let pr = (row_rate[k / 512].0 / row_rate[k / 512].1).clamp(1e-4, 1.0 - 1e-4);
            let pg = global.clamp(1e-4, 1.0 - 1e-4);
            let f = |p: f64| if dropped { -p.ln() } else { -(1.0 - p).ln() };
            nll_global += f(pg);
            nll_row += f(pr);
        }
    }
    // The decode above saw which pixels returned; here it sees nothing of every other
    // 32-column block (returns and drops alike), and x_n is scored on those blocks only.
    let hidden = |k: usize| (k % 512 / 32) % 2 == 1;
    let blind: Vec<(f64, f64, f64, usize)> = scans[..fast_n]
        .par_iter()
        .enumerate()
        .map(|(i, s)| -> Result<(f64, f64, f64, usize)> {
            let mut img = s.image.clone();
            for (k, r) in img.range_m.iter_mut().enumerate() {
                if hidden(k) {
                    *r = 0.0;
                }
            }
            let d = fast.decode(&img, i as u64)?;
            let (_, raw) = d.depth_and_keep_logits(&fast);
            let (mut cal, mut unc, mut row, mut n) = (0.0, 0.0, 0.0, 0);
            for k in (0..s.image.len()).filter(|k| hidden(*k)) {
                let kept = s.image.range_m[k] > 0.0;
                let keep = f64::from(1.0 - d.model.drop_prob[k]).clamp(1e-4, 1.0 - 1e-4);
                cal += bernoulli_nll((keep / (1.0 - keep)).ln(), kept);
                unc += bernoulli_nll(f64::from(raw[k]), kept);
                let pr = (row_rate[k / 512].0 / row_rate[k / 512].1).clamp(1e-4, 1.0 - 1e-4);
                row += bernoulli_nll(((1.0 - pr) / pr).ln(), kept);
                n += 1;
            }
            Ok((cal, unc, row, n))
        })
        .collect::<Result<_>>()?;
    let n_blind = blind.iter().map(|b| b.3).sum::<usize>().max(1) as f64;
    let n = n_pix.max(1) as f64;
    let calibration = json!({
        "hidden_blocks": {
            "nll_xn": blind.iter().map(|b| b.0).sum::<f64>() / n_blind,
            "nll_xn_uncalibrated": blind.iter().map(|b| b.1).sum::<f64>() / n_blind,
            "nll_per_row_rate": blind.iter().map(|b| b.2).sum::<f64>() / n_blind,
            "pixels": n_blind,
        },
        "nll_xn": nll / n, "nll_xn_uncalibrated": nll_raw / n,
        "calibration": fast.calibration_source(), "nll_global_rate": nll_global / n, "nll_per_row_rate": nll_row / n,
        "drop_rate_heldout": rows_drop.iter().map(|r| r.0).sum::<f64>() / n,
        "drop_rate_train": global,
        "reliability": rel.json(),
        "reliability_uncalibrated": rel_raw.json(),
    });
    eprintln!("calibration: {calibration}");
    if let Some(png) = &args.png {
        reliability_chart(png, &rel, &rel_raw)?;
    }
    if args.only_raydrop {
        println!("{}", serde_json::to_string_pretty(&calibration)?);
        return Ok(());
    }

    // ---- Upsampling and restoration (fast decoding from sparse observations) -------------
    let variants = default_variants();
    let sparse = sparse_cases(&args, &fast, &scans[..fast_n], &variants)?;
    // The same from `paper` decodes (minutes per scan): does a longer inversion close the gap?
    let paper_rows = if args.sparse_paper_scans > 0 {
        let n = args.sparse_paper_scans.min(scans.len());
        let r16 = lines_case(&args, &scans[..n], 16, Quality::Paper, &variants)?;
        let r8 = lines_case(&args, &scans[..n], 8, Quality::Paper, &variants)?;
        eprintln!("paper: upsample rows 16->64: {r16}; restore 8 of 64 lines: {r8}");
        json!({"upsample_rows_16_to_64_mae_m": r16, "restore_8_of_64_lines_mae_m": r8})
    } else {
        serde_json::Value::Null
    };

    let results = json!({
        "reconstruction": reconstruction,
        "calibration": calibration,
        "upsampling_and_restoration": sparse,
        "paper_decodes_of_sparse_rows": paper_rows,
    });
    write_report(&args, header, results)
}

/// Prints `header` merged with `results` as JSON (and writes it to `--out`).
fn write_report(args: &Args, header: serde_json::Value, results: serde_json::Value) -> Result<()> {
    let mut report = header;
    if let (Some(r), Some(add)) = (report.as_object_mut(), results.as_object()) {
        r.extend(add.clone());
    }
    let text = serde_json::to_string_pretty(&report)?;
    if let Some(out) = &args.out {
        std::fs::write(out, &text).with_context(|| format!("failed to write {}", out.display()))?;
    }
    println!("{text}");
    Ok(())
}

/// A reliability curve: per x_n bin, the summed x_n, the drops and the pixel count.
struct Reliability(Vec<(f64, f64, usize)>);

impl Reliability {
    fn new(bins: usize) -> Self {
        Reliability(vec![(0.0, 0.0, 0); bins])
    }

    fn add(&mut self, x_n: f64, dropped: bool) {
        let n = self.0.len();
        let bin = &mut self.0[((x_n * n as f64) as usize).min(n - 1)];
        bin.0 += x_n;
        bin.1 += f64::from(u8::from(dropped));
        bin.2 += 1;
    }

    /// Observed drop rate per bin; NaN where a bin has too few pixels to say.
    fn observed(&self) -> Vec<f64> {
        self.0
            .iter()
            .map(|(_, d, c)| if *c >= 100 { d / *c as f64 } else { f64::NAN })
            .collect()
    }

    fn json(&self) -> serde_json::Value {
        let n = self.0.len() as f64;
        self.0
            .iter()
            .enumerate()
            .map(|(i, (sp, sd, c))| {
                json!({
                    "bin": format!("{:.1}-{:.1}", i as f64 / n, (i + 1) as f64 / n),
                    "pixels": c, "mean_xn": sp / (*c).max(1) as f64,
                    "observed_drop_rate": sd / (*c).max(1) as f64,
                })
            })
            .collect()
    }
}

/// The reliability curves of the calibrated and the raw x_n against the diagonal.
fn reliability_chart(path: &Path, calibrated: &Reliability, raw: &Reliability) -> Result<()> {
    use rangegan_mcap::report::plot::{FITTED, LineChart, SIM, Series, line_chart};
    use rangegan_mcap::util::fs::write_atomic;
    let n = calibrated.0.len();
    let x: Vec<f64> = (0..n).map(|i| (i as f64 + 0.5) / n as f64).collect();
    let (cal, unc) = (calibrated.observed(), raw.observed());
    let chart = LineChart {
        title: "Ray-drop calibration, 26 held-out KITTI scans",
        x_label: "predicted drop probability x_n (bin centre)",
        y_label: "observed drop rate",
        x: &x,
        series: &[
            Series {
                label: "calibrated x_n (shipped)",
                colour: FITTED,
                y: &cal,
            },
            Series {
                label: "raw x_n of the generator",
                colour: SIM,
                y: &unc,
            },
            Series {
                label: "perfect calibration",
                colour: plotters::style::RGBColor(120, 120, 120),
                y: &x,
            },
        ],
    };
    write_atomic(path, &line_chart(&chart)?)
        .with_context(|| format!("failed to write {}", path.display()))
}

/// Per method over all scans: MAE, MAE near (<= 30 m) and far, and the share of pixels more
/// than 1 m off.
fn summarize(per: &[Vec<ErrorSums>], names: &[String]) -> serde_json::Value {
    let mut m = serde_json::Map::new();
    let mut total = ErrorSums::default();
    for (i, name) in names.iter().enumerate() {
        let mut t = ErrorSums::default();
        for p in per {
            t.add(&p[i]);
        }
        m.insert(
            name.clone(),
            json!({
                "mae": t.mae(),
                "mae_near": t.near / t.near_n.max(1) as f64,
                "mae_far": t.far / t.far_n.max(1) as f64,
                "off_1m": t.off_1m as f64 / t.n().max(1) as f64,
                "holes": t.holes as f64 / t.n().max(1) as f64,
            }),
        );
        total = t;
    }
    m.insert("pixels".into(), json!(total.n()));
    m.insert("near_pixels".into(), json!(total.near_n));
    m.insert("far_pixels".into(), json!(total.far_n));
    m.insert("scans".into(), json!(per.len()));
    serde_json::Value::Object(m)
}

/// The method names of a case: `baselines` then the variants.
fn names(baselines: &[&str], variants: &[Variant]) -> Vec<String> {
    baselines
        .iter()
        .map(|b| b.to_string())
        .chain(variants.iter().map(|v| v.name.clone()))
        .collect()
}

/// Upsampling 16 -> 64 beams / restoration from `n_lines` of 64 rows: decode from the kept
/// rows, fill the others.
fn lines_case(
    args: &Args,
    scans: &[Scan],
    n_lines: usize,
    quality: Quality,
    variants: &[Variant],
) -> Result<serde_json::Value> {
    let grid512 = model_grid();
    let mut opts = DecodeOptions::new(quality);
    opts.restore = Some(Sparsify::Lines(n_lines));
    let d = decoder(&args.model, &args.encoder, opts, &args.fast_schedule)?;
    let kept = Sparsify::kept_rows(n_lines, 64);
    let per: Vec<Vec<ErrorSums>> = scans
        .par_iter()
        .enumerate()
        .map(|(i, s)| -> Result<Vec<ErrorSums>> {
            let dec = d.decode(&s.image, i as u64)?;
            let sparse = rows_image(&s.image, &kept);
            let near = resample_image(&sparse, &grid512, Interpolation::Nearest).range_m;
            let bil = resample_image(&sparse, &grid512, Interpolation::Bilinear).range_m;
            let gan_sparse = rows_image(&with_validity_of(&s.image, &dec.model.depth_m), &kept);
            let bil_gan = resample_image(&gan_sparse, &grid512, Interpolation::Bilinear).range_m;
            let (add, mul) = anchored(&dec.model.depth_m, &bil, &bil_gan);
            let filled: Vec<Vec<f32>> = variants
                .iter()
                .map(|v| dec.interpolate_restored(v.fill, &v.rule))
                .collect();
            let observed: Vec<f32> = (0..s.image.range_m.len())
                .map(|k| {
                    if kept.contains(&(k / 512)) {
                        s.image.range_m[k]
                    } else {
                        0.0
                    }
                })
                .collect();
            let column = column_linear(&observed, &s.image.angles.elevation_rad, 64, 512);
            let fallback = nearest_in_column_then_row(&observed, 64, 512);
            let baselines = [&dec.model.depth_m, &near, &bil, &column, &add, &mul];
            let preds = with_fallbacks(&baselines, &fallback, &filled, &dec.model.depth_m);
            let held = |k: usize| !kept.contains(&(k / 512));
            Ok(errors(&s.image.range_m, &preds, &held))
        })
        .collect::<Result<_>>()?;
    Ok(summarize(&per, &names(&LINE_BASELINES, variants)))
}

/// Restoration from a random 10 % of the measured pixels.
fn fraction_case(args: &Args, scans: &[Scan], variants: &[Variant]) -> Result<serde_json::Value> {
    let mut opts = DecodeOptions::new(Quality::Fast);
    opts.restore = Some(Sparsify::Fraction(0.1));
    let d = decoder(&args.model, &args.encoder, opts, &args.fast_schedule)?;
    let per: Vec<Vec<ErrorSums>> = scans
        .par_iter()
        .enumerate()
        .map(|(i, s)| -> Result<Vec<ErrorSums>> {
            let dec = d.decode(&s.image, i as u64)?;
            let (near, idw) = scattered_baselines(&dec.observed_m, 64, 512);
            let gan_obs: Vec<f32> = dec
                .observed_m
                .iter()
                .zip(&dec.model.depth_m)
                .map(|(o, g)| if *o > 0.0 { *g } else { 0.0 })
                .collect();
            let (_, idw_gan) = scattered_baselines(&gan_obs, 64, 512);
            let (add, mul) = anchored(&dec.model.depth_m, &idw, &idw_gan);
            let filled: Vec<Vec<f32>> = variants
                .iter()
                .map(|v| dec.interpolate_restored(v.fill, &v.rule))
                .collect();
            let column = column_linear(&dec.observed_m, &s.image.angles.elevation_rad, 64, 512);
            let fallback = nearest_in_column_then_row(&dec.observed_m, 64, 512);
            let baselines = [&dec.model.depth_m, &near, &idw, &column, &add, &mul];
            let preds = with_fallbacks(&baselines, &fallback, &filled, &dec.model.depth_m);
            let held = |k: usize| dec.held_out_m[k] > 0.0;
            Ok(errors(&s.image.range_m, &preds, &held))
        })
        .collect::<Result<_>>()?;
    Ok(summarize(
        &per,
        &names(
            &[
                "gan_fast",
                "nearest",
                "idw",
                "column_linear",
                "anchored_add",
                "anchored_mul",
            ],
            variants,
        ),
    ))
}

/// Upsampling 512 -> 2048 columns on the full-resolution scans (truth: their 64 x 2048
/// projection).
fn columns_case(fast: &Decoder, scans: &[Scan], variants: &[Variant]) -> Result<serde_json::Value> {
    let grid2048 = SensorProfile::kitti_hdl64e()
        .with_columns(2048)
        .angle_grid();
    let full: Vec<&Scan> = scans.iter().filter(|s| s.full.is_some()).collect();
    let prepared = fast.prepare(&grid2048);
    let per: Vec<Vec<ErrorSums>> = full
        .par_iter()
        .enumerate()
        .map(|(i, s)| -> Result<Vec<ErrorSums>> {
            let truth = s
                .full
                .as_ref()
                .map(|f| f.range_m.clone())
                .unwrap_or_default();
            let dec = fast.decode(&s.image, 1000 + i as u64)?;
            let dense = dec.render_prepared(&prepared);
            let near = resample_image(&s.image, &grid2048, Interpolation::Nearest).range_m;
            let bil = resample_image(&s.image, &grid2048, Interpolation::Bilinear).range_m;
            let gan512 = with_validity_of(&s.image, &dec.model.depth_m);
            let bil_gan = resample_image(&gan512, &grid2048, Interpolation::Bilinear).range_m;
            let (add, mul) = anchored(&dense.depth_m, &bil, &bil_gan);
            let filled: Vec<Vec<f32>> = variants
                .iter()
                .map(|v| dec.interpolate_on(&dense, v.fill, &v.rule))
                .collect();
            let fallback = nearest_in_column_then_row(&near, 64, 2048);
            let baselines = [&dense.depth_m, &near, &bil, &add, &mul];
            let preds = with_fallbacks(&baselines, &fallback, &filled, &dense.depth_m);
            Ok(errors(&truth, &preds, &|_| true))
        })
        .collect::<Result<_>>()?;
    Ok(summarize(&per, &names(&GRID_BASELINES, variants)))
}

/// The four upsampling / restoration cases.
fn sparse_cases(
    args: &Args,
    fast: &Decoder,
    scans: &[Scan],
    variants: &[Variant],
) -> Result<serde_json::Value> {
    let rows16 = lines_case(args, scans, 16, Quality::Fast, variants)?;
    eprintln!("upsample rows 16->64: {rows16}");
    let rows8 = lines_case(args, scans, 8, Quality::Fast, variants)?;
    eprintln!("restore 8 of 64 lines: {rows8}");
    let fraction = fraction_case(args, scans, variants)?;
    eprintln!("restore 10 % of points: {fraction}");
    let columns = columns_case(fast, scans, variants)?;
    eprintln!("upsample columns 512->2048: {columns}");
    Ok(json!({
        "upsample_rows_16_to_64_mae_m": rows16,
        "upsample_columns_512_to_2048_mae_m": columns,
        "restore_8_of_64_lines_mae_m": rows8,
        "restore_10_percent_points_mae_m": fraction,
    }))
}

/// Every rule of a small grid, for the guided and the edge-aware fill, on training scans;
/// prints each variant's MAE per case relative to the case's bilinear (IDW) baseline.
fn tune(args: &Args, fast: &Decoder, n: usize) -> Result<()> {
    let scans = load_training_scans(&args.data, n)?;
    eprintln!(
        "tuning on {} training scans ({} full resolution)",
        scans.len(),
        scans.iter().filter(|s| s.full.is_some()).count()
    );
    let mut variants = Vec::new();
    for inverse_depth in [false, true] {
        let inv = if inverse_depth { " 1/d" } else { "" };
        for jump_per_deg in [0.2f32, 0.3, 0.5] {
            for trust_below_deg in [0.0f32, 1.0, 1.5] {
                let jump = jump_per_deg;
                let t = trust_below_deg;
                variants.push(Variant {
                    name: format!("edge_aware j={jump} t={t}{inv}"),
                    fill: Fill::EdgeAware,
                    rule: SurfaceRule {
                        jump_per_deg,
                        trust_below_deg,
                        inverse_depth,
                        ..SurfaceRule::default()
                    },
                });
                for guide_jump in [0.1f32, 0.2, 0.3] {
                    variants.push(Variant {
                        name: format!("guided j={jump} t={t} g={guide_jump}{inv}"),
                        fill: Fill::Guided,
                        rule: SurfaceRule {
                            jump_per_deg,
                            guide_jump,
                            trust_below_deg,
                            inverse_depth,
                        },
                    });
                }
            }
        }
    }
    let cases = sparse_cases(args, fast, &scans, &variants)?;
    let keys = [
        ("upsample_rows_16_to_64_mae_m", "bilinear"),
        ("upsample_columns_512_to_2048_mae_m", "bilinear"),
        ("restore_8_of_64_lines_mae_m", "bilinear"),
        ("restore_10_percent_points_mae_m", "idw"),
    ];
    println!("| variant | 16->64 | 512->2048 | 8 lines | 10 % | mean ratio to bilinear/IDW |");
    println!("|---|---|---|---|---|---|");
    for v in &variants {
        let mut cells = Vec::new();
        let mut ratios = Vec::new();
        for (case, base) in keys {
            let mae = cases[case][&v.name]["mae"].as_f64().unwrap_or(f64::NAN);
            let b = cases[case][base]["mae"].as_f64().unwrap_or(f64::NAN);
            // Cases without ground truth on the training scans (no full-resolution ones
            // for 512 -> 2048) are left out of the mean.
            if b > 0.0 {
                ratios.push(mae / b);
            }
            cells.push(format!("{mae:.3}"));
        }
        let ratio = ratios.iter().sum::<f64>() / ratios.len().max(1) as f64;
        println!("| {} | {} | {ratio:.3} |", v.name, cells.join(" | "));
    }
    for (case, base) in keys {
        println!(
            "{case}: {base} {:.3}",
            cases[case][base]["mae"].as_f64().unwrap_or(f64::NAN)
        );
    }
    Ok(())
}
