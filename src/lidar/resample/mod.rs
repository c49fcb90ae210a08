//! Resampling on the sphere: angle grids to another H x W (the GAN's 2x/4x
//! upsampling) and range images onto another grid (another resolution or another
//! sensor's profile), with nearest and bilinear baselines.
//!
//! Grids use pixel-centre alignment ("align corners = false"): output pixel `(i', j')`
//! reads the source at row `(i' + 0.5) H / H' - 0.5` and column
//! `(j' + 0.5) W / W' - 0.5`. Under this alignment a regular grid of the reference
//! convention `pi - (j + 0.5) 2pi / W` resizes exactly to the regular grid of the new
//! width. Angles are interpolated as (cos, sin) pairs and recovered with `atan2`, so
//! the azimuth seam at +-pi needs no special case, and columns wrap around.
//!
//! `grid` resizes angle grids and sensor profiles; this file resamples range images.

mod grid;
#[cfg(test)]
mod tests;

use super::range_image::NO_POINT;
use super::surface::{Guide, Neighbour, SurfaceRule, blend_depth, keep_surface, renormalise};
use super::{AngleGrid, RangeImage, SensorProfile};

/// How [`resample_image`] reads the source image.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Interpolation {
    /// The source pixel whose centre is nearest (by grid coordinates). Keeps the
    /// measured return: xyz, intensity, label and point index come along.
    Nearest,
    /// Bilinear over the four surrounding pixels, using only the valid ones
    /// (weights renormalised), so no range is ever averaged with an empty pixel.
    /// A target pixel is valid exactly when its nearest source pixel is: the drop
    /// pattern is the nearest-neighbour one and only the values are smoothed.
    Bilinear,
}

impl Interpolation {
    pub fn name(self) -> &'static str {
        match self {
            Interpolation::Nearest => "nearest",
            Interpolation::Bilinear => "bilinear",
        }
    }
}

/// Source coordinate of output index `k` of `n_out` on an axis of `n_in` samples.
fn source_coord(k: usize, n_out: usize, n_in: usize) -> f32 {
    (k as f32 + 0.5) * n_in as f32 / n_out as f32 - 0.5
}

/// Locates directions of a target grid in a source grid's (fractional) row and
/// column coordinates.
struct Locator {
    /// Row elevations, top first (decreasing).
    rows: Vec<f32>,
    /// Column azimuth offsets from column 0, unwrapped to increasing values in
    /// [0, 2pi), plus 2pi for column 0 again to close the circle.
    col_offsets: Vec<f32>,
    azimuth0: f32,
}

impl Locator {
    fn new(grid: &AngleGrid) -> Self {
        let rows = grid.row_elevations();
        let azimuths = grid.column_azimuths();
        let azimuth0 = azimuths.first().copied().unwrap_or(0.0);
        let tau = std::f32::consts::TAU;
        // Columns run clockwise (decreasing azimuth): offset = azimuth0 - azimuth.
        let mut col_offsets: Vec<f32> = azimuths
            .iter()
            .map(|a| (azimuth0 - a).rem_euclid(tau))
            .collect();
        col_offsets.push(tau);
        Locator {
            rows,
            col_offsets,
            azimuth0,
        }
    }

    /// Fractional row of elevation `phi`; rows are pixel-sized, so anything beyond
    /// half a row spacing outside the table is outside the field of view.
    fn row(&self, phi: f32) -> Option<f32> {
        let r = &self.rows;
        match r.len() {
            0 => None,
            1 => Some(0.0),
            n => {
                // Rows decrease; find the first row at or below phi.
                let k = r.partition_point(|&e| e > phi);
                let u = if k == 0 {
                    (r[0] - phi) / (r[0] - r[1])
                } else if k == n {
                    (n - 2) as f32 + (r[n - 2] - phi) / (r[n - 2] - r[n - 1])
                } else {
                    (k - 1) as f32 + (r[k - 1] - phi) / (r[k - 1] - r[k])
                };
                (u.is_finite() && (-0.5..=n as f32 - 0.5).contains(&u)).then_some(u)
            }
        }
    }

    /// Fractional column of azimuth `theta`, in [0, W).
    fn column(&self, theta: f32) -> f32 {
        let w = self.col_offsets.len() - 1;
        let off = (self.azimuth0 - theta).rem_euclid(std::f32::consts::TAU);
        let k = self.col_offsets.partition_point(|&o| o <= off).clamp(1, w);
        let (o0, o1) = (self.col_offsets[k - 1], self.col_offsets[k]);
        let frac = if o1 > o0 { (off - o0) / (o1 - o0) } else { 0.0 };
        ((k - 1) as f32 + frac).rem_euclid(w as f32)
    }
}

/// `image` resampled onto `target` (any grid: `image.angles.resized(2 * h, 4 * w)`,
/// another sensor's `profile.angle_grid()`, ...).
///
/// Each target pixel's direction is located in the source grid (row by elevation,
/// column by azimuth, circular); directions more than half a row outside the
/// source's elevation range stay empty. With [`Interpolation::Nearest`] the pixel
/// takes the nearest source pixel as is (measured xyz included). With
/// [`Interpolation::Bilinear`] range and intensity are blended over the valid
/// corners only, xyz is the range along the target direction, the label comes from
/// the heaviest valid corner and `point_index` is [`NO_POINT`] (no single source
/// point stands for the pixel).
pub fn resample_image(image: &RangeImage, target: &AngleGrid, method: Interpolation) -> RangeImage {
    match method {
        Interpolation::Nearest => resample_with(image, target, Read::Nearest),
        Interpolation::Bilinear => resample_with(image, target, Read::Bilinear),
    }
}

/// `image` resampled onto `target` like [`Interpolation::Bilinear`] (same pixels valid),
/// but a new pixel blends only the corners on its own surface ([`SurfaceRule`]): the
/// nearest corner's, or with a `guide` (e.g. the decoded scene's completed depth on both
/// grids) the one the guide puts the new pixel on. No range is averaged across a depth
/// edge, and a target pixel where a measured return lies keeps that return exactly (xyz,
/// intensity, label and point index included): a target pixel on a source pixel's
/// direction, or, on a finer azimuth grid, the pixel the return's own azimuth falls in.
pub fn resample_by_surface(
    image: &RangeImage,
    target: &AngleGrid,
    rule: &SurfaceRule,
    guide: Option<Guide<'_>>,
) -> RangeImage {
    resample_with(image, target, Read::Surface(rule, guide))
}

/// How [`resample_with`] reads the source around a target pixel.
enum Read<'a> {
    Nearest,
    Bilinear,
    Surface(&'a SurfaceRule, Option<Guide<'a>>),
}

/// Direction of a target pixel closer than this (in source pixels, on each axis) to a source
/// pixel's direction keeps that pixel's return as is.
const ON_SOURCE_PIXEL: f32 = 1e-3;

fn resample_with(image: &RangeImage, target: &AngleGrid, read: Read<'_>) -> RangeImage {
    let mut out = RangeImage::empty(target.clone());
    let (h, w) = (image.height, image.width);
    let n = h * w;
    let consistent = [
        image.range_m.len(),
        image.xyz.len(),
        image.intensity.len(),
        image.label.len(),
        image.point_index.len(),
    ]
    .iter()
    .all(|&l| l == n)
        && image.angles.height == h
        && image.angles.width == w
        && image.angles.len() == n
        && target.elevation_rad.len() == target.len()
        && target.azimuth_rad.len() == target.len();
    if n == 0 || !consistent {
        return out;
    }
    let locate = Locator::new(&image.angles);
    let (placed, measured_v) = match read {
        Read::Surface(..) => {
            let azimuths = measured_azimuths(image);
            let columns = azimuths.iter().map(|&a| locate.column(a)).collect();
            (place_measured(image, &azimuths, target), columns)
        }
        Read::Nearest | Read::Bilinear => (Vec::new(), Vec::new()),
    };
    let mut corners: Vec<Neighbour> = Vec::with_capacity(4);
    for k in 0..target.len() {
        if let Some(&Some(from)) = placed.get(k) {
            copy_pixel(image, from, &mut out, k);
            continue;
        }
        let Some(u) = locate.row(target.elevation_rad[k]) else {
            continue;
        };
        let v = locate.column(target.azimuth_rad[k]);
        let u = u.clamp(0.0, (h - 1) as f32);
        let nearest = (u.round() as usize).min(h - 1) * w + (v.round() as usize) % w;
        if !image.is_valid(nearest) {
            continue;
        }
        let on_source =
            (u - u.round()).abs() < ON_SOURCE_PIXEL && (v - v.round()).abs() < ON_SOURCE_PIXEL;
        let blend = match &read {
            Read::Nearest => false,
            Read::Bilinear => true,
            Read::Surface(..) => !on_source,
        };
        if !blend {
            copy_pixel(image, nearest, &mut out, k);
            continue;
        }
        valid_corners(image, u, v, &measured_v, &mut corners);
        let mut inverse = false;
        if let Read::Surface(rule, guide) = &read {
            if (u - u.round()).abs() < ON_SOURCE_PIXEL {
                behind_own_return(image, nearest, &mut corners);
            }
            for c in corners.iter_mut() {
                c.guide = guide.map_or(0.0, |g| g.source(c.index));
            }
            let one = keep_surface(&mut corners, guide.map_or(0.0, |g| g.target(k)), rule);
            inverse = rule.inverse_depth && one;
        }
        // The nearest corner is valid and weighs >= 1/4, so something is left.
        if corners.is_empty() {
            continue;
        }
        let d = blend_depth(&corners, inverse);
        let [x, y, z] = target.direction(k);
        out.range_m[k] = d;
        out.xyz[k] = [d * x, d * y, d * z];
        out.intensity[k] = corners
            .iter()
            .map(|c| c.weight * image.intensity[c.index])
            .sum();
        out.label[k] = corners
            .iter()
            .max_by(|a, b| a.weight.total_cmp(&b.weight))
            .map_or(0, |c| image.label[c.index]);
        out.point_index[k] = NO_POINT;
    }
    out
}

/// For each target pixel, the measured return that lies in it, if any: a return on a source
/// row that is also a target row goes to the target column its measured azimuth falls in,
/// the nearest return winning, as projection decides a pixel. A source pixel holds the
/// nearest of the returns anywhere in its (wider) azimuth span, so this puts it where it
/// was measured instead of blending it into every finer pixel of that span.
fn place_measured(image: &RangeImage, azimuths: &[f32], target: &AngleGrid) -> Vec<Option<usize>> {
    let mut placed: Vec<Option<usize>> = vec![None; target.len()];
    let (h, w) = (target.height, target.width);
    if h == 0 || w == 0 {
        return placed;
    }
    let locate = Locator::new(target);
    let source_rows = image.angles.row_elevations();
    for (i, &azimuth) in azimuths.iter().enumerate() {
        if azimuth.is_nan() {
            continue;
        }
        let Some(u) = source_rows
            .get(i / image.width)
            .and_then(|&phi| locate.row(phi))
        else {
            continue;
        };
        if (u - u.round()).abs() > ON_SOURCE_PIXEL {
            continue;
        }
        let v = locate.column(azimuth);
        let k = (u.round() as usize).min(h - 1) * w + (v.round() as usize) % w;
        if placed[k].is_none_or(|j| image.range_m[i] < image.range_m[j]) {
            placed[k] = Some(i);
        }
    }
    placed
}

/// A target pixel on a source row lies inside source pixel `own`'s azimuth span, and
/// projection kept the nearest of the returns in that span: whatever this pixel holds is
/// at least as far as `own`'s return. So a corner nearer than that return (the other
/// side of a depth edge, or a surface sloping towards the sensor) is not read. Applies
/// only where `own` holds a measured return (not a rendered or filled one).
fn behind_own_return(image: &RangeImage, own: usize, corners: &mut Vec<Neighbour>) {
    if image.point_index[own] == NO_POINT {
        return;
    }
    let floor = image.range_m[own];
    corners.retain(|c| c.index == own || c.depth >= floor);
    renormalise(corners);
}

/// Copies source pixel `from` (the measured return as is) to target pixel `to`.
fn copy_pixel(image: &RangeImage, from: usize, out: &mut RangeImage, to: usize) {
    out.range_m[to] = image.range_m[from];
    out.xyz[to] = image.xyz[from];
    out.intensity[to] = image.intensity[from];
    out.label[to] = image.label[from];
    out.point_index[to] = image.point_index[from];
}

const MIN_CORNER_WEIGHT: f32 = 1e-4;

/// The azimuth of each source pixel's measured return, NaN where the pixel holds no
/// measured point.
fn measured_azimuths(image: &RangeImage) -> Vec<f32> {
    (0..image.range_m.len())
        .map(|i| {
            let [x, y, _] = image.xyz[i];
            let measured =
                image.is_valid(i) && image.point_index[i] != NO_POINT && (x != 0.0 || y != 0.0);
            if measured { y.atan2(x) } else { f32::NAN }
        })
        .collect()
}

/// Where target column `v` lies between the returns of source pixels `a` (column `c0`) and
/// `b` (the next column), 0 at `a`'s return and 1 at `b`'s: by their measured azimuths where
/// both have one (`measured_v`), else by their pixel centres.
fn column_share(measured_v: &[f32], a: usize, b: usize, c0: usize, v: f32, w: usize) -> f32 {
    let s = v - v.floor();
    let (Some(&ma), Some(&mb)) = (measured_v.get(a), measured_v.get(b)) else {
        return s;
    };
    if !(ma.is_finite() && mb.is_finite()) {
        return s;
    }
    // Offsets of the returns from their pixel centres, in columns (circular).
    let wrap = |d: f32| (d + w as f32 / 2.0).rem_euclid(w as f32) - w as f32 / 2.0;
    let (da, db) = (wrap(ma - c0 as f32), wrap(mb - (c0 + 1) as f32));
    let span = 1.0 + db - da;
    if span < 1e-3 {
        return s;
    }
    ((s - da) / span).clamp(0.0, 1.0)
}

/// The valid ones of the four source pixels around `(u, v)` with their bilinear weights,
/// renormalised to sum 1 (columns circular, rows clamped). Along a row the weights follow the
/// returns' measured azimuths where `measured_v` has them.
fn valid_corners(
    image: &RangeImage,
    u: f32,
    v: f32,
    measured_v: &[f32],
    corners: &mut Vec<Neighbour>,
) {
    let (h, w) = (image.height, image.width);
    let r0 = (u.floor() as usize).min(h - 1);
    let r1 = (r0 + 1).min(h - 1);
    let c0 = (v.floor() as usize) % w;
    let c1 = (c0 + 1) % w;
    let t = u - r0 as f32;
    let s0 = column_share(measured_v, r0 * w + c0, r0 * w + c1, c0, v, w);
    let s1 = column_share(measured_v, r1 * w + c0, r1 * w + c1, c0, v, w);
    corners.clear();
    for (index, weight) in [
        (r0 * w + c0, (1.0 - t) * (1.0 - s0)),
        (r0 * w + c1, (1.0 - t) * s0),
        (r1 * w + c0, t * (1.0 - s1)),
        (r1 * w + c1, t * s1),
    ] {
        // Weights of float noise (a target row on a source row) would add a corner of
        // another beam, so a corner needs a real share.
        if image.is_valid(index) && weight > MIN_CORNER_WEIGHT {
            corners.push(Neighbour {
                index,
                depth: image.range_m[index],
                weight,
                direction: image.angles.direction(index),
                guide: 0.0,
            });
        }
    }
    renormalise(corners);
}

/// `image` resampled onto `profile`'s grid (another sensor, or the same sensor at
/// another resolution).
pub fn resample_to_profile(
    image: &RangeImage,
    profile: &SensorProfile,
    method: Interpolation,
) -> RangeImage {
    resample_image(image, &profile.angle_grid(), method)
}
