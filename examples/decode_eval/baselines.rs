//! The interpolation baselines the decoder's fills are measured against, and the
//! fallbacks that score a pixel a method leaves empty.

use rangegan_mcap::lidar::{AngleGrid, RangeImage};

/// The interpolation baselines of the upsampling and row-restoration tasks, in order.
/// The baselines of the row cases: the grid ones with per-column linear interpolation.
pub(crate) const LINE_BASELINES: [&str; 6] = [
    "gan_fast",
    "nearest",
    "bilinear",
    "column_linear",
    "anchored_add",
    "anchored_mul",
];

pub(crate) const GRID_BASELINES: [&str; 5] = [
    "gan_fast",
    "nearest",
    "bilinear",
    "anchored_add",
    "anchored_mul",
];

/// The predictions of a case with their fallbacks: the interpolation baselines fall back to
/// the nearest return (`nearest`), `convert`'s fills to the rendering x_d (`x_d`), as
/// `convert` completes them.
pub(crate) fn with_fallbacks<'a>(
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
pub(crate) fn nearest_in_column_then_row(observed: &[f32], h: usize, w: usize) -> Vec<f32> {
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
pub(crate) fn column_linear(
    observed: &[f32],
    elevation_rad: &[f32],
    h: usize,
    w: usize,
) -> Vec<f32> {
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
pub(crate) fn rows_image(img: &RangeImage, rows: &[usize]) -> RangeImage {
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
pub(crate) fn scattered_baselines(observed: &[f32], h: usize, w: usize) -> (Vec<f32>, Vec<f32>) {
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
pub(crate) fn anchored(gan: &[f32], base_obs: &[f32], base_gan: &[f32]) -> (Vec<f32>, Vec<f32>) {
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
pub(crate) fn with_validity_of(like: &RangeImage, values: &[f32]) -> RangeImage {
    let mut out = like.clone();
    for (k, r) in out.range_m.iter_mut().enumerate() {
        if *r > 0.0 {
            *r = values[k];
        }
    }
    out
}
