//! Sliced Wasserstein distance between two sets of range images, paper protocol: Laplacian
//! pyramid (3 levels), 7x7 patches, 128 patches per image per level, descriptors normalised per
//! set, 4 x 128 random projections, mean |sorted(a) - sorted(b)|. Host code, no burn.

use crate::util::rng::Rng;

/// SWD settings (defaults are the paper's).
#[derive(Debug, Clone)]
pub struct SwdConfig {
    pub levels: usize,
    pub patch: usize,
    pub patches_per_image: usize,
    pub repeats: usize,
    pub projections: usize,
    pub seed: u64,
}

impl Default for SwdConfig {
    fn default() -> Self {
        Self {
            levels: 3,
            patch: 7,
            patches_per_image: 128,
            repeats: 4,
            projections: 128,
            seed: 0,
        }
    }
}

/// [1,4,6,4,1]/16 blur (circular along W, replicate along H) then stride-2 decimation.
fn pyr_down(x: &[f32], h: usize, w: usize) -> Vec<f32> {
    const K: [f32; 5] = [1.0 / 16.0, 4.0 / 16.0, 6.0 / 16.0, 4.0 / 16.0, 1.0 / 16.0];
    let (h2, w2) = (h / 2, w / 2);
    let mut out = vec![0f32; h2 * w2];
    for i in 0..h2 {
        for j in 0..w2 {
            let mut acc = 0.0;
            for (a, ka) in K.iter().enumerate() {
                let r = (2 * i + a).saturating_sub(2).min(h - 1);
                for (b, kb) in K.iter().enumerate() {
                    let c = (2 * j + w + b - 2) % w;
                    acc += ka * kb * x[r * w + c];
                }
            }
            out[i * w2 + j] = acc;
        }
    }
    out
}

/// Nearest-neighbour-free 2x upsampling matching `pyr_down` (zero insertion + 4x the filter).
fn pyr_up(x: &[f32], h: usize, w: usize) -> Vec<f32> {
    const K: [f32; 5] = [1.0 / 16.0, 4.0 / 16.0, 6.0 / 16.0, 4.0 / 16.0, 1.0 / 16.0];
    let (h2, w2) = (2 * h, 2 * w);
    let mut out = vec![0f32; h2 * w2];
    for i in 0..h2 {
        for j in 0..w2 {
            let mut acc = 0.0;
            for (a, ka) in K.iter().enumerate() {
                let ri = i as isize + a as isize - 2;
                if ri.rem_euclid(2) != 0 {
                    continue;
                }
                let r = (ri.div_euclid(2)).clamp(0, h as isize - 1) as usize;
                for (b, kb) in K.iter().enumerate() {
                    let cj = j as isize + b as isize - 2;
                    if cj.rem_euclid(2) != 0 {
                        continue;
                    }
                    let c = cj.div_euclid(2).rem_euclid(w as isize) as usize;
                    acc += 4.0 * ka * kb * x[r * w + c];
                }
            }
            out[i * w2 + j] = acc;
        }
    }
    out
}

/// Laplacian pyramid, finest first; the last level is the low-pass residual.
pub fn laplacian_pyramid(
    x: &[f32],
    h: usize,
    w: usize,
    levels: usize,
) -> Vec<(usize, usize, Vec<f32>)> {
    let mut out = Vec::with_capacity(levels);
    let (mut cur, mut ch, mut cw) = (x.to_vec(), h, w);
    for l in 0..levels {
        if l + 1 == levels {
            out.push((ch, cw, cur));
            break;
        }
        let down = pyr_down(&cur, ch, cw);
        let up = pyr_up(&down, ch / 2, cw / 2);
        let lap: Vec<f32> = cur.iter().zip(&up).map(|(a, b)| a - b).collect();
        out.push((ch, cw, lap));
        cur = down;
        ch /= 2;
        cw /= 2;
    }
    out
}

/// Random patches of every image at every level: `descriptors[level]` is a flat list of
/// patch*patch vectors.
fn descriptors(
    images: &[&[f32]],
    h: usize,
    w: usize,
    cfg: &SwdConfig,
    rng: &mut Rng,
) -> Vec<Vec<Vec<f32>>> {
    let mut out = vec![Vec::new(); cfg.levels];
    for img in images {
        for (l, (lh, lw, lap)) in laplacian_pyramid(img, h, w, cfg.levels)
            .into_iter()
            .enumerate()
        {
            let p = cfg.patch.min(lh);
            for _ in 0..cfg.patches_per_image {
                let r0 = rng.below(lh - p + 1);
                let c0 = rng.below(lw); // circular along azimuth
                let mut d = Vec::with_capacity(p * p);
                for r in 0..p {
                    for c in 0..p {
                        d.push(lap[(r0 + r) * lw + (c0 + c) % lw]);
                    }
                }
                out[l].push(d);
            }
        }
    }
    out
}

/// Zero mean, unit standard deviation over the whole set (as in the ProGAN SWD code).
fn normalise(desc: &mut [Vec<f32>]) {
    let n = desc.iter().map(|d| d.len()).sum::<usize>().max(1) as f64;
    let mean = desc.iter().flatten().map(|&v| v as f64).sum::<f64>() / n;
    let var = desc
        .iter()
        .flatten()
        .map(|&v| (v as f64 - mean).powi(2))
        .sum::<f64>()
        / n;
    let std = var.sqrt().max(1e-8);
    for d in desc.iter_mut() {
        for v in d.iter_mut() {
            *v = ((*v as f64 - mean) / std) as f32;
        }
    }
}

fn sliced(a: &[Vec<f32>], b: &[Vec<f32>], cfg: &SwdConfig, rng: &mut Rng) -> f64 {
    let n = a.len().min(b.len());
    let dim = a.first().map(|d| d.len()).unwrap_or(0);
    if n == 0 || dim == 0 {
        return 0.0;
    }
    let mut total = 0.0;
    for _ in 0..cfg.repeats {
        let mut sum = 0.0;
        for _ in 0..cfg.projections {
            let mut dir: Vec<f32> = (0..dim).map(|_| rng.normal()).collect();
            let norm = dir.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-12);
            dir.iter_mut().for_each(|v| *v /= norm);
            let project = |set: &[Vec<f32>]| -> Vec<f32> {
                let mut p: Vec<f32> = set[..n]
                    .iter()
                    .map(|d| d.iter().zip(&dir).map(|(x, y)| x * y).sum())
                    .collect();
                p.sort_by(|x, y| x.total_cmp(y));
                p
            };
            let (pa, pb) = (project(a), project(b));
            sum += pa
                .iter()
                .zip(&pb)
                .map(|(x, y)| (x - y).abs() as f64)
                .sum::<f64>()
                / n as f64;
        }
        total += sum / cfg.projections as f64;
    }
    total / cfg.repeats as f64
}

/// SWD per pyramid level (finest first) between two sets of `[H, W]` images.
pub fn swd(a: &[&[f32]], b: &[&[f32]], h: usize, w: usize, cfg: &SwdConfig) -> Vec<f64> {
    let mut rng = Rng::new(cfg.seed);
    let mut da = descriptors(a, h, w, cfg, &mut rng);
    let mut db = descriptors(b, h, w, cfg, &mut rng);
    (0..cfg.levels)
        .map(|l| {
            normalise(&mut da[l]);
            normalise(&mut db[l]);
            sliced(&da[l], &db[l], cfg, &mut rng)
        })
        .collect()
}

/// SWD (per level, finest first, and their mean) between a run's EMA samples and real scans.
#[derive(Debug, Clone, serde::Serialize)]
pub struct SwdReport {
    pub per_level: Vec<f64>,
    pub mean: f64,
    pub fake_images: usize,
    pub real_images: usize,
}

impl SwdReport {
    fn new(per_level: Vec<f64>, fake_images: usize, real_images: usize) -> Self {
        let mean = per_level.iter().sum::<f64>() / per_level.len().max(1) as f64;
        Self {
            per_level,
            mean,
            fake_images,
            real_images,
        }
    }
}

/// Inverse depth x_d of a set of images in network units (what the paper's SWD compares;
/// dropped pixels count as 0).
fn inverse_depth(images: &[f32]) -> Vec<f32> {
    images.iter().map(|v| ((v + 1.0) * 0.5).max(0.0)).collect()
}

/// SWD between `n_fake` samples (after ray drop) of `model` and the scans of
/// `real` (e.g. the held-out sequences), on the inverse depth.
pub fn swd_of_model(
    model: &super::weights::Model,
    real: &super::data::RangeDataset,
    n_fake: usize,
    cfg: &SwdConfig,
    device: &burn::tensor::Device,
) -> anyhow::Result<SwdReport> {
    let opts = super::sample::SampleOptions {
        n: n_fake,
        seed: cfg.seed ^ 0xfa6e,
        truncation: 1.0,
        grid: Some(real.angles.clone()),
    };
    let fakes: Vec<Vec<f32>> = super::sample::sample(model, &opts, device)?
        .into_iter()
        .map(|s| {
            s.x_d
                .iter()
                .zip(&s.mask)
                .map(|(x, &m)| if m { *x } else { 0.0 })
                .collect()
        })
        .collect();
    let reals = inverse_depth(&real.images);
    let n = real.height * real.width;
    let a: Vec<&[f32]> = fakes.iter().map(|f| f.as_slice()).collect();
    let b: Vec<&[f32]> = reals.chunks_exact(n).collect();
    let per_level = swd(&a, &b, real.height, real.width, cfg);
    Ok(SwdReport::new(per_level, a.len(), b.len()))
}

/// The floor: SWD between two real sets (e.g. training scans vs held-out scans).
pub fn swd_between(
    a: &super::data::RangeDataset,
    b: &super::data::RangeDataset,
    cfg: &SwdConfig,
) -> SwdReport {
    let (ia, ib) = (inverse_depth(&a.images), inverse_depth(&b.images));
    let n = a.height * a.width;
    let sa: Vec<&[f32]> = ia.chunks_exact(n).collect();
    let sb: Vec<&[f32]> = ib.chunks_exact(n).collect();
    SwdReport::new(swd(&sa, &sb, a.height, a.width, cfg), sa.len(), sb.len())
}

/// Points of a set's returns, as the paper's point-set metrics see them: back-projected on
/// `angles`, farthest-point sampled to `n_points` and scaled by 1/80 m.
pub fn point_sets(
    images: &[&[f32]],
    angles: &crate::lidar::AngleGrid,
    n_points: usize,
) -> Vec<Vec<[f32; 3]>> {
    use rayon::prelude::*;
    images
        .par_iter()
        .map(|img| {
            let range = super::data::network_to_range(img);
            let points: Vec<[f32; 3]> = range
                .iter()
                .enumerate()
                .filter(|(_, d)| **d > 0.0)
                .map(|(k, d)| {
                    let (el, az) = (angles.elevation_rad[k], angles.azimuth_rad[k]);
                    let r = d / super::data::MAX_DEPTH_M;
                    [
                        r * el.cos() * az.cos(),
                        r * el.cos() * az.sin(),
                        r * el.sin(),
                    ]
                })
                .collect();
            farthest_point_sample(&points, n_points)
        })
        .collect()
}

/// Farthest-point sampling from the first point (deterministic); all points if there are
/// fewer than `k`.
pub fn farthest_point_sample(points: &[[f32; 3]], k: usize) -> Vec<[f32; 3]> {
    if points.len() <= k {
        return points.to_vec();
    }
    let mut nearest = vec![f32::INFINITY; points.len()];
    let mut picked = Vec::with_capacity(k);
    let mut next = 0;
    for _ in 0..k {
        let p = points[next];
        picked.push(p);
        let mut far = (0, -1.0f32);
        for (i, q) in points.iter().enumerate() {
            let d = dist2(p, *q).min(nearest[i]);
            nearest[i] = d;
            if d > far.1 {
                far = (i, d);
            }
        }
        next = far.0;
    }
    picked
}

fn dist2(a: [f32; 3], b: [f32; 3]) -> f32 {
    (a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)
}

/// Chamfer distance: mean squared distance to the nearest point of the other set, both ways.
pub fn chamfer(a: &[[f32; 3]], b: &[[f32; 3]]) -> f64 {
    let one_way = |x: &[[f32; 3]], y: &[[f32; 3]]| -> f64 {
        let sum: f64 = x
            .iter()
            .map(|p| {
                y.iter()
                    .map(|q| dist2(*p, *q))
                    .fold(f32::INFINITY, f32::min) as f64
            })
            .sum();
        sum / x.len().max(1) as f64
    };
    one_way(a, b) + one_way(b, a)
}

/// 1-nearest-neighbour accuracy (the paper's 1-NNA, here with the Chamfer distance): each set
/// member is labelled by its nearest neighbour in the union of both sets without itself; the
/// accuracy is 0.5 when the sets are indistinguishable and 1.0 when they are apart.
pub fn one_nna(generated: &[Vec<[f32; 3]>], real: &[Vec<[f32; 3]>]) -> f64 {
    use rayon::prelude::*;
    let all: Vec<(&[[f32; 3]], bool)> = generated
        .iter()
        .map(|p| (p.as_slice(), true))
        .chain(real.iter().map(|p| (p.as_slice(), false)))
        .collect();
    let correct = (0..all.len())
        .into_par_iter()
        .filter(|&i| {
            let nn = (0..all.len())
                .filter(|&j| j != i)
                .map(|j| (chamfer(all[i].0, all[j].0), j))
                .min_by(|a, b| a.0.total_cmp(&b.0))
                .map(|(_, j)| j);
            nn.is_some_and(|j| all[j].1 == all[i].1)
        })
        .count();
    correct as f64 / all.len().max(1) as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    fn images(seed: u64, n: usize, h: usize, w: usize, freq: f32) -> Vec<Vec<f32>> {
        let mut rng = Rng::new(seed);
        (0..n)
            .map(|_| {
                let phase = rng.uniform() * std::f32::consts::TAU;
                (0..h * w)
                    .map(|k| ((k % w) as f32 * freq + phase).sin() + 0.1 * rng.normal())
                    .collect()
            })
            .collect()
    }

    #[test]
    fn laplacian_pyramid_sums_back_to_the_image_for_constants() {
        let x = vec![0.7f32; 16 * 32];
        let pyr = laplacian_pyramid(&x, 16, 32, 3);
        assert_eq!(pyr.len(), 3);
        assert_eq!((pyr[2].0, pyr[2].1), (4, 8));
        assert!(pyr[0].2.iter().all(|v| v.abs() < 1e-5));
        assert!(pyr[2].2.iter().all(|v| (v - 0.7).abs() < 1e-5));
    }

    fn slices(v: &[Vec<f32>]) -> Vec<&[f32]> {
        v.iter().map(|x| x.as_slice()).collect()
    }

    fn cloud(rng: &mut Rng, n: usize, centre: [f32; 3]) -> Vec<[f32; 3]> {
        (0..n)
            .map(|_| centre.map(|c| c + 0.1 * rng.normal()))
            .collect()
    }

    #[test]
    fn one_nna_is_half_for_one_distribution_and_one_for_two() {
        let mut rng = Rng::new(4);
        let a: Vec<_> = (0..10).map(|_| cloud(&mut rng, 64, [0.0; 3])).collect();
        let a2: Vec<_> = (0..10).map(|_| cloud(&mut rng, 64, [0.0; 3])).collect();
        let b: Vec<_> = (0..10)
            .map(|_| cloud(&mut rng, 64, [1.0, 0.0, 0.0]))
            .collect();
        assert_eq!(one_nna(&a, &b), 1.0);
        let same = one_nna(&a, &a2);
        assert!((0.2..=0.8).contains(&same), "{same}");
    }

    #[test]
    fn farthest_point_sampling_spreads_out() {
        let pts: Vec<[f32; 3]> = (0..100).map(|i| [i as f32, 0.0, 0.0]).collect();
        let s = farthest_point_sample(&pts, 3);
        assert_eq!(s, vec![[0.0, 0.0, 0.0], [99.0, 0.0, 0.0], [49.0, 0.0, 0.0]]);
        assert_eq!(farthest_point_sample(&pts[..2], 3).len(), 2);
    }

    #[test]
    fn swd_is_small_within_a_distribution_and_larger_across() {
        let cfg = SwdConfig {
            patches_per_image: 64,
            projections: 32,
            ..Default::default()
        };
        let (h, w) = (16, 64);
        let a = images(1, 8, h, w, 0.3);
        let a2 = images(2, 8, h, w, 0.3);
        let b = images(3, 8, h, w, 1.3);
        let same: f64 = swd(&slices(&a), &slices(&a2), h, w, &cfg).iter().sum();
        let diff: f64 = swd(&slices(&a), &slices(&b), h, w, &cfg).iter().sum();
        assert!(diff > 2.0 * same, "same {same} diff {diff}");
    }
}
