//! The scans the spatial-latent model learns from, and the observations it is shown.
//!
//! Sources, each on its own sensor grid: KITTI at full resolution (64 x 2048 range images),
//! KITTI scans stored at every fourth point (64 x 512) and simulated scans of every built-in
//! sensor family (16-128 beams, fields of view from +-15 deg to +-45 deg). Whole recordings are
//! held out for validation.
//!
//! Each training example hides some of the truth from the encoder: rays marked unknown (stripes
//! of columns as in decoding, random rays, whole beams as in restoration) and holes (patches,
//! beams, sectors, object shapes) that either look like drops or are unknown, so completion is
//! what it learns. Every true return is a target for x_d; the drop probability is scored on
//! the unknown rays.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail, ensure};
use rayon::prelude::*;

use crate::lidar::holes::HoleKind;
use crate::lidar::{AngleGrid, SensorProfile, Strategy};
use crate::model::spatial::decode::{STRIPE, hiding_pass};
use crate::model::spatial::{
    OWN_FEATURES, Observation, Query, Ray, SpatialConfig, base_log_depths, encoder_input,
    grid_queries, own_features,
};
use crate::sim::{SceneConfig, Simulator};
use crate::util::rng::Rng;

/// Scans on one sensor grid.
#[derive(Debug, Clone)]
pub struct Source {
    pub name: String,
    pub angles: AngleGrid,
    /// Range in metres per scan, row-major; 0 = no return.
    pub scans: Vec<Vec<f32>>,
    /// Real scans teach x_n; simulated ones have no sensor drops to learn from.
    pub real: bool,
}

impl Source {
    fn new(name: &str, angles: AngleGrid, scans: Vec<Vec<f32>>, real: bool) -> Result<Self> {
        ensure!(!scans.is_empty(), "no scans for '{name}'");
        ensure!(
            scans.iter().all(|s| s.len() == angles.len()),
            "'{name}': a scan is not {} x {}",
            angles.height,
            angles.width
        );
        Ok(Source {
            name: name.into(),
            angles,
            scans,
            real,
        })
    }
}

/// The full-resolution KITTI folder (64 x 2048 16-bit PNG range images, value / 256 = m).
pub const FULLRES_FOLDER: &str = "kitti_fullres_drive_c";
/// Its every-fourth-point copy: the same scenes, so it is never trained beside it.
pub const FULLRES_TWIN: &str = "kitti_raw_drive_c";
/// The 512-column KITTI drive held out whole for validation.
pub const VALIDATION_DRIVE: &str = "kitti_raw_drive_g";
/// Frames of the full-resolution drive from here on are validation (its last 1.6 s).
pub const FULLRES_VALIDATION_FROM: usize = 120;

/// Reads one full-resolution KITTI range image.
pub fn read_fullres_png(path: &Path) -> Result<Vec<f32>> {
    let file = std::fs::File::open(path)
        .with_context(|| format!("failed to open '{}'", path.display()))?;
    let mut decoder = png::Decoder::new(std::io::BufReader::new(file));
    decoder.set_transformations(png::Transformations::IDENTITY);
    let mut reader = decoder
        .read_info()
        .with_context(|| format!("'{}' is not a PNG", path.display()))?;
    let info = reader.info();
    ensure!(
        info.bit_depth == png::BitDepth::Sixteen
            && info.color_type == png::ColorType::Grayscale
            && (info.width, info.height) == (2048, 64),
        "'{}' is not a 64 x 2048 16-bit grayscale range image",
        path.display()
    );
    let mut buf = vec![0u8; reader.output_buffer_size().unwrap_or(64 * 2048 * 2)];
    let frame = reader
        .next_frame(&mut buf)
        .with_context(|| format!("failed to decode '{}'", path.display()))?;
    Ok(buf[..frame.buffer_size()]
        .chunks_exact(2)
        .map(|b| u16::from_be_bytes([b[0], b[1]]) as f32 / 256.0)
        .collect())
}

/// The grid of the full-resolution KITTI images.
pub fn fullres_angles() -> AngleGrid {
    SensorProfile::kitti_hdl64e()
        .with_columns(2048)
        .angle_grid()
}

fn files_with(dir: &Path, ext: &str) -> Result<Vec<PathBuf>> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("failed to list '{}'", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == ext))
        .collect();
    v.sort();
    Ok(v)
}

/// Full-resolution KITTI: (training frames, validation frames).
pub fn fullres_sources(real_lidar: &Path) -> Result<(Source, Source)> {
    let files = files_with(&real_lidar.join(FULLRES_FOLDER), "png")?;
    ensure!(
        files.len() > FULLRES_VALIDATION_FROM,
        "'{}' holds {} range images; expected more than {FULLRES_VALIDATION_FROM}",
        real_lidar.join(FULLRES_FOLDER).display(),
        files.len()
    );
    let scans: Vec<Vec<f32>> = files
        .par_iter()
        .map(|f| read_fullres_png(f))
        .collect::<Result<_>>()?;
    let (train, val) = scans.split_at(FULLRES_VALIDATION_FROM);
    Ok((
        Source::new("kitti 64x2048", fullres_angles(), train.to_vec(), true)?,
        Source::new(
            "kitti 64x2048 (validation)",
            fullres_angles(),
            val.to_vec(),
            true,
        )?,
    ))
}

/// KITTI scans stored at every fourth point, on the 64 x 512 grid: (training, validation).
pub fn kitti_512_sources(real_lidar: &Path) -> Result<(Source, Source)> {
    let (train, val) = crate::model::data::kitti_validation_split(
        real_lidar,
        &[FULLRES_TWIN.to_string(), VALIDATION_DRIVE.to_string()],
    )?;
    let twin = real_lidar.join(FULLRES_TWIN);
    let val: Vec<PathBuf> = val.into_iter().filter(|f| !f.starts_with(&twin)).collect();
    let profile = SensorProfile::kitti_hdl64e().with_columns(512);
    let project = |files: &[PathBuf]| -> Result<Vec<Vec<f32>>> {
        files
            .par_iter()
            .map(|path| {
                let scan = crate::lidar::kitti::read_bin(path)
                    .with_context(|| format!("failed to read '{}'", path.display()))?;
                let image = crate::lidar::project(&scan, &profile, Strategy::Auto)
                    .with_context(|| format!("failed to project '{}'", path.display()))?;
                ensure!(
                    (image.height, image.width) == (64, 512),
                    "'{}' projected to {} x {}",
                    path.display(),
                    image.height,
                    image.width
                );
                Ok(image.range_m)
            })
            .collect()
    };
    Ok((
        Source::new("kitti 64x512", profile.angle_grid(), project(&train)?, true)?,
        Source::new(
            "kitti 64x512 (validation)",
            profile.angle_grid(),
            project(&val)?,
            true,
        )?,
    ))
}

/// Sensors the simulated scans cover, with their columns: every built-in family, 16-128 beams.
pub const SIMULATED_SENSORS: [(&str, usize); 10] = [
    ("vlp16", 1024),
    ("hdl32e", 1024),
    ("vlp32c", 1024),
    ("pandarxt32", 1024),
    ("pandar64", 1024),
    ("hdl64e", 2048),
    ("os0-64", 1024),
    ("os1-128", 1024),
    ("os2-32", 1024),
    ("os1-64", 512),
];

/// `per_sensor` ideal simulated scans of each of [`SIMULATED_SENSORS`], half a second apart,
/// from scenes of their own (seeded by the sensor's place in the list).
pub fn simulated_sources(per_sensor: usize, seed: u64) -> Result<Vec<Source>> {
    SIMULATED_SENSORS
        .iter()
        .enumerate()
        .map(|(s, &(name, columns))| {
            let profile = SensorProfile::builtin(name)
                .map_err(|e| anyhow::anyhow!("{e}"))?
                .with_columns(columns);
            let scans: Vec<Vec<f32>> = (0..per_sensor)
                .into_par_iter()
                .map(|i| {
                    // A new street every four scans.
                    let scene = seed + 1000 * s as u64 + (i / 4) as u64;
                    let sim = Simulator::new(
                        SceneConfig {
                            seed: scene,
                            duration_s: 2.2,
                            ..Default::default()
                        },
                        profile.clone(),
                    );
                    sim.scan(5 * (i % 4) as u32).image.range_m
                })
                .collect();
            Source::new(
                &format!("simulated {name} {columns}"),
                profile.angle_grid(),
                scans,
                false,
            )
        })
        .collect()
}

/// One batch: scans of one source cropped to the same columns, as the encoder's input and
/// the targets of every query (the crop's pixels, row-major).
#[derive(Debug, Clone)]
pub struct Batch {
    pub size: usize,
    pub inputs: Vec<f32>,
    pub input_shape: [usize; 2],
    pub circular: bool,
    pub queries: Vec<Query>,
    /// Per example and query: what the encoder was shown of the query's own ray,
    /// `[size, queries, OWN_FEATURES]`.
    pub own_rays: Vec<f32>,
    /// Per example and query: the log depth its rendering corrects.
    pub base: Vec<f32>,
    /// Per example and query: ln(true range) where a true return, else 0.
    pub log_range: Vec<f32>,
    /// 1 where a true return the encoder saw.
    pub seen_return: Vec<f32>,
    /// 1 where a true return the encoder did not see (unknown or cut).
    pub hidden_return: Vec<f32>,
    /// 1 where the ray was unknown to the encoder (its drop probability is scored).
    pub unknown: Vec<f32>,
    /// 1 where the ray truly returned.
    pub returned: Vec<f32>,
}

/// How much of the truth a training example hides.
#[derive(Debug, Clone, Copy)]
pub struct Hiding {
    /// Probability of holes.
    pub cut: f32,
    /// Share of holes that are unknown rather than drops (x_n learns inside them).
    pub unknown_holes: f32,
    /// Share of the crop's rays that are queries (the rest are neither rendered nor scored).
    pub query_share: f32,
    /// Share of examples whose ranges are scaled by a factor from 0.15 to 1.2 (log-uniform):
    /// a street seen at a tenth of its size looks like a room or a car park, which the
    /// streets of the training data do not show.
    pub rescale: f32,
}

/// Draws a batch of `size` examples of `source`, each `crop` columns wide (or the whole turn).
pub fn batch(
    source: &Source,
    size: usize,
    crop: usize,
    config: &SpatialConfig,
    hiding: Hiding,
    rng: &mut Rng,
) -> Result<Batch> {
    let (h, w) = (source.angles.height, source.angles.width);
    if w == 0 || h == 0 {
        bail!("'{}' has an empty grid", source.name);
    }
    let crop = crop.min(w);
    let whole = crop == w;
    let start = if whole { 0 } else { rng.below(w) };
    let angles = crop_angles(&source.angles, start, crop);
    let all_queries = grid_queries(&angles);
    let picked: Vec<usize> = (0..h * crop)
        .filter(|_| rng.chance(hiding.query_share))
        .collect();
    let n = picked.len();
    let mut b = Batch {
        size,
        inputs: Vec::new(),
        input_shape: [0, 0],
        circular: whole && crate::model::spatial::decode::wraps(&angles),
        queries: picked.iter().map(|&q| all_queries[q]).collect(),
        own_rays: Vec::with_capacity(size * n * OWN_FEATURES),
        base: Vec::with_capacity(size * n),
        log_range: Vec::with_capacity(size * n),
        seen_return: Vec::with_capacity(size * n),
        hidden_return: Vec::with_capacity(size * n),
        unknown: Vec::with_capacity(size * n),
        returned: Vec::with_capacity(size * n),
    };
    for _ in 0..size {
        let mut range = source.scans[rng.below(source.scans.len())].clone();
        if rng.chance(hiding.rescale) {
            let scale = rng.range(0.15f32.ln(), 1.2f32.ln()).exp();
            range.iter_mut().for_each(|r| *r *= scale);
        }
        if rng.chance(0.5) {
            mirror(&mut range, h, w);
        }
        let mut cut = if rng.chance(hiding.cut) {
            let kind = HoleKind::ALL[rng.below(HoleKind::ALL.len())];
            kind.cut(&range, h, w, rng)
        } else {
            vec![false; h * w]
        };
        let mut unknown = unknown_rays(h, w, rng);
        if rng.chance(hiding.unknown_holes) {
            for (u, c) in unknown.iter_mut().zip(cut.iter_mut()) {
                *u |= std::mem::take(c);
            }
        }
        let at = |q: usize| (q / crop) * w + (start + q % crop) % w;
        let returns = |k: usize| range[k] > config.min_range_m && range[k] <= config.max_range_m;
        let rays: Vec<Ray> = (0..h * crop)
            .map(|q| {
                let k = at(q);
                if unknown[k] {
                    Ray::Unknown
                } else if cut[k] || !returns(k) {
                    Ray::Dropped
                } else {
                    Ray::Return(range[k])
                }
            })
            .collect();
        let observation = Observation {
            rays: &rays,
            angles: &angles,
            circular: b.circular,
        };
        let own = own_features(&observation, config);
        let base = base_log_depths(&own);
        for &q in &picked {
            b.own_rays
                .extend_from_slice(&own[q * OWN_FEATURES..(q + 1) * OWN_FEATURES]);
            b.base.push(base[q]);
            let k = at(q);
            let ret = returns(k);
            let hidden = unknown[k] || cut[k];
            b.log_range.push(if ret { range[k].ln() } else { 0.0 });
            b.seen_return.push(f32::from(ret && !hidden));
            b.hidden_return.push(f32::from(ret && hidden));
            b.unknown.push(f32::from(unknown[k] && source.real));
            b.returned.push(f32::from(ret));
        }
        let (x, shape) = encoder_input(&own, &angles);
        b.inputs.extend(x);
        b.input_shape = shape;
    }
    Ok(b)
}

/// Columns `start..start + crop` (wrapping) of a grid.
fn crop_angles(angles: &AngleGrid, start: usize, crop: usize) -> AngleGrid {
    let (h, w) = (angles.height, angles.width);
    let pick = |v: &[f32]| -> Vec<f32> {
        (0..h)
            .flat_map(|i| (0..crop).map(move |j| v[i * w + (start + j) % w]))
            .collect()
    };
    AngleGrid {
        height: h,
        width: crop,
        elevation_rad: pick(&angles.elevation_rad),
        azimuth_rad: pick(&angles.azimuth_rad),
    }
}

/// Mirrors a scan left to right (a drive seen in a mirror is still a drive).
fn mirror(range: &mut [f32], h: usize, w: usize) {
    for i in 0..h {
        range[i * w..(i + 1) * w].reverse();
    }
}

/// Rays marked unknown: decoding's stripes (either pass), random rays, or all beams but every
/// second or fourth (restoration); sometimes none.
fn unknown_rays(h: usize, w: usize, rng: &mut Rng) -> Vec<bool> {
    let u = rng.uniform();
    if u < 0.5 {
        let pass = rng.below(2);
        let phase = rng.below(2 * STRIPE);
        (0..h * w)
            .map(|k| hiding_pass((k % w + phase) % w) == pass)
            .collect()
    } else if u < 0.7 {
        let p = rng.range(0.05, 0.5);
        (0..h * w).map(|_| rng.chance(p)).collect()
    } else if u < 0.85 {
        let every = [2, 4][rng.below(2)];
        let phase = rng.below(every);
        (0..h * w)
            .map(|k| !(k / w + phase).is_multiple_of(every))
            .collect()
    } else {
        vec![false; h * w]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_batch_hides_what_it_scores() {
        let angles = SensorProfile::builtin("vlp16")
            .expect("vlp16")
            .with_columns(128)
            .angle_grid();
        let mut rng = Rng::new(1);
        let scans = (0..3)
            .map(|_| {
                (0..angles.len())
                    .map(|_| {
                        if rng.chance(0.9) {
                            rng.range(2.0, 50.0)
                        } else {
                            0.0
                        }
                    })
                    .collect()
            })
            .collect();
        let source = Source::new("test", angles, scans, true).expect("source");
        let config = SpatialConfig::new();
        let hiding = Hiding {
            cut: 0.5,
            unknown_holes: 0.5,
            query_share: 0.5,
            rescale: 0.3,
        };
        let b = batch(&source, 4, 64, &config, hiding, &mut rng).expect("batch");
        let n = b.queries.len();
        assert!(n > 300 && n < 700, "{n} queries of 1024");
        assert_eq!(b.input_shape, [16, 64]);
        assert_eq!(b.inputs.len(), 4 * 12 * 16 * 64);
        assert_eq!(b.own_rays.len(), 4 * n * OWN_FEATURES);
        for k in 0..4 * n {
            // A true return is either seen or hidden; never both.
            assert_eq!(b.seen_return[k] + b.hidden_return[k], b.returned[k]);
            if b.unknown[k] > 0.0 {
                assert_eq!(b.seen_return[k], 0.0);
            }
        }
        let hidden: f32 = b.hidden_return.iter().sum();
        assert!(hidden > 0.0);
    }
}
