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

/// Bilinear interpolation of unit vectors `(cos a, sin a)` of an angle field given
/// at four corners (top-left, top-right, bottom-left, bottom-right), returning the
/// angle. `t` runs along rows, `s` along columns; weights may fall outside [0, 1]
/// (row extrapolation).
fn lerp_angle(a: [(f32, f32); 4], t: f32, s: f32) -> f32 {
    let w = [(1.0 - t) * (1.0 - s), (1.0 - t) * s, t * (1.0 - s), t * s];
    let (mut c, mut si) = (0.0f32, 0.0f32);
    for ((ck, sk), wk) in a.iter().zip(w) {
        c += wk * ck;
        si += wk * sk;
    }
    si.atan2(c)
}

impl AngleGrid {
    /// The grid resampled to `height x width` (see the module doc for alignment).
    ///
    /// Elevation and azimuth are both interpolated bilinearly as (cos, sin) pairs.
    /// Columns are circular (the last column's neighbour is column 0). Rows are not:
    /// above the top row and below the bottom row the two outermost rows are
    /// extrapolated linearly, so a uniform elevation table stays uniform when
    /// upsampled (clamping would repeat the edge elevation).
    pub fn resized(&self, height: usize, width: usize) -> AngleGrid {
        let (h, w) = (self.height, self.width);
        let mut elevation_rad = Vec::with_capacity(height * width);
        let mut azimuth_rad = Vec::with_capacity(height * width);
        if h == 0 || w == 0 || self.elevation_rad.len() < h * w || self.azimuth_rad.len() < h * w {
            return AngleGrid {
                height: 0,
                width: 0,
                elevation_rad,
                azimuth_rad,
            };
        }
        // (cos, sin) of every source angle, computed once.
        let unit = |field: &[f32]| -> Vec<(f32, f32)> {
            field[..h * w].iter().map(|a| (a.cos(), a.sin())).collect()
        };
        let (elevation_unit, azimuth_unit) = (unit(&self.elevation_rad), unit(&self.azimuth_rad));
        for i in 0..height {
            let u = source_coord(i, height, h);
            // Two rows that bracket u (or the two outermost ones), t relative to r0.
            let r0 = if h == 1 {
                0
            } else {
                (u.floor().max(0.0) as usize).min(h - 2)
            };
            let r1 = (r0 + 1).min(h - 1);
            let t = if r1 == r0 { 0.0 } else { u - r0 as f32 };
            for j in 0..width {
                let v = source_coord(j, width, w).rem_euclid(w as f32);
                let c0 = (v.floor() as usize).min(w - 1);
                let c1 = (c0 + 1) % w;
                let s = v - c0 as f32;
                let at = |field: &[(f32, f32)]| {
                    [
                        field[r0 * w + c0],
                        field[r0 * w + c1],
                        field[r1 * w + c0],
                        field[r1 * w + c1],
                    ]
                };
                elevation_rad.push(lerp_angle(at(&elevation_unit), t, s));
                azimuth_rad.push(lerp_angle(at(&azimuth_unit), t, s));
            }
        }
        AngleGrid {
            height,
            width,
            elevation_rad,
            azimuth_rad,
        }
    }

    /// Circular mean elevation of each row (exact for the separable grids that
    /// profiles and [`AngleGrid::resized`] produce).
    pub fn row_elevations(&self) -> Vec<f32> {
        (0..self.height)
            .map(|i| circular_mean((0..self.width).map(|j| self.elevation_rad[i * self.width + j])))
            .collect()
    }

    /// Circular mean azimuth of each column.
    pub fn column_azimuths(&self) -> Vec<f32> {
        (0..self.width)
            .map(|j| circular_mean((0..self.height).map(|i| self.azimuth_rad[i * self.width + j])))
            .collect()
    }
}

impl SensorProfile {
    /// The same sensor resampled to `beams x columns`: the elevation table is
    /// interpolated like [`AngleGrid::resized`] (so `profile.resampled(h, w).angle_grid()`
    /// equals `profile.angle_grid().resized(h, w)`), range limits are kept. Per-beam
    /// azimuth offsets are dropped, as resampled beams are not physical lasers.
    pub fn resampled(&self, beams: usize, columns: usize) -> SensorProfile {
        let grid =
            AngleGrid::regular_columns(self.beams(), 1, |i| self.elevation_deg[i].to_radians());
        let rows = grid.resized(beams, 1).row_elevations();
        SensorProfile {
            name: format!("{}@{}x{}", self.name, beams, columns),
            elevation_deg: rows.iter().map(|e| e.to_degrees()).collect(),
            azimuth_offset_deg: None,
            columns,
            min_range_m: self.min_range_m,
            max_range_m: self.max_range_m,
        }
    }
}

fn circular_mean(angles: impl Iterator<Item = f32>) -> f32 {
    let (mut c, mut s) = (0.0f64, 0.0f64);
    for a in angles {
        c += f64::from(a.cos());
        s += f64::from(a.sin());
    }
    s.atan2(c) as f32
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

#[cfg(test)]
mod tests {
    use super::super::range_image::column_azimuth;
    use super::*;

    fn uniform_profile(beams: usize, columns: usize, top: f32, bottom: f32) -> SensorProfile {
        let step = (top - bottom) / (beams - 1) as f32;
        SensorProfile {
            name: "uniform".into(),
            elevation_deg: (0..beams).map(|i| top - step * i as f32).collect(),
            azimuth_offset_deg: None,
            columns,
            min_range_m: 0.5,
            max_range_m: 100.0,
        }
    }

    fn angle_diff(a: f32, b: f32) -> f32 {
        super::super::profile::wrap_pi(a - b).abs()
    }

    #[test]
    fn regular_columns_resize_exactly_and_uniform_rows_stay_uniform() {
        // 16 beams, 2 deg apart; 2x rows and 4x columns.
        let p = uniform_profile(16, 256, 15.0, -15.0);
        let g = p.angle_grid().resized(32, 1024);
        assert_eq!((g.height, g.width), (32, 1024));
        for j in [0usize, 1, 511, 512, 1023] {
            assert!(
                angle_diff(g.azimuth_rad[5 * 1024 + j], column_azimuth(j, 1024)) < 1e-5,
                "column {j}"
            );
        }
        // Pixel-centre alignment: new rows at source coordinates i/2 - 0.25, i.e.
        // 1 deg apart starting half a new row above the old top row.
        for i in 0..32 {
            let expect = (15.0 + 0.5 - i as f32).to_radians();
            assert!(
                (g.elevation_rad[i * 1024 + 7] - expect).abs() < 1e-5,
                "row {i}: {} vs {expect}",
                g.elevation_rad[i * 1024 + 7]
            );
        }
        // Downsampling back gives the original grid.
        let back = g.resized(16, 256);
        let orig = p.angle_grid();
        for k in 0..orig.len() {
            assert!(angle_diff(back.azimuth_rad[k], orig.azimuth_rad[k]) < 1e-5);
            assert!((back.elevation_rad[k] - orig.elevation_rad[k]).abs() < 1e-5);
        }
    }

    #[test]
    fn azimuth_interpolation_is_circular_across_the_seam() {
        // Two columns at +170 and -170 deg (via a custom grid): midpoints must be at
        // +-180, not 0, which a plain lerp of the angles would give.
        let g = AngleGrid {
            height: 1,
            width: 2,
            elevation_rad: vec![0.0, 0.0],
            azimuth_rad: vec![170f32.to_radians(), (-170f32).to_radians()],
        };
        let r = g.resized(1, 4);
        // Output column 1 reads source column 0.25 (from +170 towards -170 across
        // +-180); column 3 reads 1.25, i.e. from -170 back towards +170.
        for a in &r.azimuth_rad {
            assert!(
                a.abs() > 160f32.to_radians(),
                "azimuth {} deg leaked to the front",
                a.to_degrees()
            );
        }
        // A quarter of the way along the 20 deg arc (interpolating the chord, then
        // atan2, lands within 0.05 deg of the arc's quarter point).
        assert!(
            angle_diff(r.azimuth_rad[1], 175f32.to_radians()) < 0.05f32.to_radians(),
            "{}",
            r.azimuth_rad[1].to_degrees()
        );
        assert!(
            angle_diff(r.azimuth_rad[3], (-175f32).to_radians()) < 0.05f32.to_radians(),
            "{}",
            r.azimuth_rad[3].to_degrees()
        );
    }

    #[test]
    fn profile_resampling_matches_grid_resizing() {
        let p = SensorProfile::kitti_hdl64e().with_columns(512);
        let q = p.resampled(128, 2048);
        assert_eq!((q.beams(), q.columns), (128, 2048));
        assert!(q.elevation_deg.windows(2).all(|w| w[0] > w[1]));
        let a = q.angle_grid();
        let b = p.angle_grid().resized(128, 2048);
        for k in (0..a.len()).step_by(97) {
            assert!((a.elevation_rad[k] - b.elevation_rad[k]).abs() < 1e-5);
            assert!(angle_diff(a.azimuth_rad[k], b.azimuth_rad[k]) < 1e-5);
        }
        // Each new row pair brackets its old row: rows 2i and 2i+1 straddle row i.
        for i in 1..63 {
            assert!(
                q.elevation_deg[2 * i] > p.elevation_deg[i]
                    && q.elevation_deg[2 * i + 1] < p.elevation_deg[i]
            );
        }
    }

    /// A range image on a uniform profile whose range is a smooth function of the
    /// direction, with a hole.
    fn smooth_image(p: &SensorProfile) -> RangeImage {
        let mut img = RangeImage::empty(p.angle_grid());
        for k in 0..img.len() {
            let (phi, theta) = (img.angles.elevation_rad[k], img.angles.azimuth_rad[k]);
            let d = 20.0 + 5.0 * theta.cos() + 30.0 * phi;
            img.range_m[k] = d;
            let [x, y, z] = img.angles.direction(k);
            img.xyz[k] = [d * x, d * y, d * z];
            img.intensity[k] = 1.0;
            img.label[k] = 7;
            img.point_index[k] = k as u32;
        }
        img
    }

    #[test]
    fn identity_resampling_returns_the_image() {
        let p = uniform_profile(8, 64, 10.0, -10.0);
        let img = smooth_image(&p);
        for m in [Interpolation::Nearest, Interpolation::Bilinear] {
            let out = resample_to_profile(&img, &p, m);
            for k in 0..img.len() {
                assert!(
                    (out.range_m[k] - img.range_m[k]).abs() < 1e-3,
                    "{} pixel {k}",
                    m.name()
                );
            }
        }
        let nearest = resample_to_profile(&img, &p, Interpolation::Nearest);
        assert_eq!(nearest.point_index, img.point_index);
    }

    #[test]
    fn bilinear_upsampling_is_closer_than_nearest_on_smooth_scenes() {
        let p = uniform_profile(8, 64, 10.0, -10.0);
        let img = smooth_image(&p);
        let fine = p.angle_grid().resized(8, 256);
        let truth =
            |k: usize| 20.0 + 5.0 * fine.azimuth_rad[k].cos() + 30.0 * fine.elevation_rad[k];
        let err = |m| {
            let out = resample_image(&img, &fine, m);
            assert_eq!(out.valid_count(), fine.len());
            (0..fine.len())
                .map(|k| (out.range_m[k] - truth(k)).abs())
                .fold(0.0f32, f32::max)
        };
        let (near, bil) = (err(Interpolation::Nearest), err(Interpolation::Bilinear));
        assert!(
            bil < 0.05 && bil < near / 5.0,
            "bilinear {bil} nearest {near}"
        );
    }

    #[test]
    fn bilinear_never_blends_with_empty_pixels() {
        let p = uniform_profile(4, 16, 3.0, -3.0);
        let mut img = RangeImage::empty(p.angle_grid());
        // Left half at 10 m, right half empty, one pixel at 30 m on row 1.
        for i in 0..4 {
            for j in 0..8 {
                img.range_m[i * 16 + j] = 10.0;
            }
        }
        img.range_m[16 + 3] = 30.0;
        let out = resample_image(
            &img,
            &p.angle_grid().resized(8, 64),
            Interpolation::Bilinear,
        );
        let mut seen_blend = false;
        for k in 0..out.len() {
            let r = out.range_m[k];
            assert!(
                r == 0.0 || (10.0 - 1e-4..=30.0 + 1e-4).contains(&r),
                "pixel {k}: {r}"
            );
            seen_blend |= r > 10.5 && r < 29.5;
        }
        assert!(
            seen_blend,
            "the 30 m pixel is blended with its valid neighbours"
        );
        // Validity follows the nearest source pixel: half the columns are valid.
        assert_eq!(out.valid_count(), out.len() / 2);
        let near = resample_image(&img, &p.angle_grid().resized(8, 64), Interpolation::Nearest);
        assert_eq!(near.valid_count(), out.valid_count());
    }

    #[test]
    fn resampling_onto_another_sensor_reads_the_right_directions() {
        // A 64-beam source, 0.5 deg apart, and a 16-beam target on the same span:
        // every target beam lies on a source row, so values are reproduced.
        let src = uniform_profile(61, 360, 15.0, -15.0);
        let img = smooth_image(&src);
        let dst = uniform_profile(16, 1024, 15.0, -15.0);
        let out = resample_to_profile(&img, &dst, Interpolation::Bilinear);
        assert_eq!(out.valid_count(), out.len());
        for k in 0..out.len() {
            let truth =
                20.0 + 5.0 * out.angles.azimuth_rad[k].cos() + 30.0 * out.angles.elevation_rad[k];
            assert!((out.range_m[k] - truth).abs() < 0.01, "pixel {k}");
            let n = out.xyz[k].iter().map(|c| c * c).sum::<f32>().sqrt();
            assert!((n - out.range_m[k]).abs() < 1e-3);
        }
        // A target reaching beyond the source's field of view stays empty there.
        let wide = uniform_profile(9, 64, 40.0, -40.0);
        let out = resample_to_profile(&img, &wide, Interpolation::Nearest);
        for i in 0..9 {
            let inside = wide.elevation_deg[i].abs() <= 15.25;
            let valid = (0..64).filter(|&j| out.is_valid(i * 64 + j)).count();
            assert_eq!(
                valid,
                if inside { 64 } else { 0 },
                "row {i} at {} deg",
                wide.elevation_deg[i]
            );
        }
    }

    /// 8 x 512: rows 0-3 a wall at 10 m, rows 4-7 the road at 40 m (slightly varying).
    fn edge_image(p: &SensorProfile) -> RangeImage {
        let mut img = smooth_image(p);
        for k in 0..img.len() {
            let d = if k / 512 < 4 {
                10.0
            } else {
                40.0 + 0.001 * (k % 512) as f32
            };
            img.range_m[k] = d;
            let [x, y, z] = img.angles.direction(k);
            img.xyz[k] = [d * x, d * y, d * z];
        }
        img
    }

    #[test]
    fn surface_resampling_never_averages_across_a_depth_edge() {
        let p = uniform_profile(8, 512, 7.0, -7.0);
        let img = edge_image(&p);
        let fine = p.angle_grid().resized(16, 512);
        let on_a_surface = |d: f32| (d - 10.0).abs() < 1e-4 || (40.0..=40.52).contains(&d);
        let bilinear = resample_image(&img, &fine, Interpolation::Bilinear);
        assert!(bilinear.range_m.iter().any(|d| !on_a_surface(*d)));
        // Without a guide, with the edge between rows (2 deg apart) trusted, the nearest row
        // decides: new rows 7 (source row 3.25) and 8 (3.75) go to the wall and to the road.
        let trusting = SurfaceRule {
            trust_below_deg: 3.0,
            ..SurfaceRule::default()
        };
        let edge = resample_by_surface(&img, &fine, &trusting, None);
        assert_eq!(edge.valid_count(), bilinear.valid_count());
        for (k, d) in edge.range_m.iter().enumerate() {
            assert!(on_a_surface(*d), "pixel {k}: {d}");
        }
        assert!(on_a_surface(edge.range_m[7 * 512 + 5]) && edge.range_m[7 * 512 + 5] < 11.0);
        assert!(edge.range_m[8 * 512 + 5] >= 40.0);
        // A guide that puts new row 7 on the road wins over the nearer wall row.
        let guide_target: Vec<f32> = (0..fine.len())
            .map(|k| if k / 512 < 7 { 11.0 } else { 38.0 })
            .collect();
        let guide_source: Vec<f32> = (0..img.len())
            .map(|k| if k / 512 < 4 { 11.0 } else { 38.0 })
            .collect();
        let guide = Some(Guide {
            target_m: &guide_target,
            source_m: &guide_source,
        });
        // With the shipped margin the guide overrides the blend only where it clearly
        // disagrees with it: new row 7 (a quarter road) goes to the road, new row 8 (three
        // quarters road) is blended, as bilinear would.
        let margin = resample_by_surface(&img, &fine, &SurfaceRule::default(), guide);
        assert!(margin.range_m[7 * 512 + 5] >= 40.0);
        assert!((margin.range_m[8 * 512 + 5] - bilinear.range_m[8 * 512 + 5]).abs() < 1e-3);
        // A guide that sees the edge exactly, trusted without a margin: never averaged.
        let exact = SurfaceRule {
            guide_jump: 0.0,
            ..SurfaceRule::default()
        };
        let guided = resample_by_surface(&img, &fine, &exact, guide);
        for (k, d) in guided.range_m.iter().enumerate() {
            assert!(on_a_surface(*d), "pixel {k}: {d}");
        }
        assert!(guided.range_m[7 * 512 + 5] >= 40.0);
        assert!((guided.range_m[6 * 512 + 5] - 10.0).abs() < 1e-4);
    }

    #[test]
    fn surface_resampling_keeps_measured_returns_exactly() {
        let p = uniform_profile(8, 512, 7.0, -7.0);
        let mut img = edge_image(&p);
        img.range_m[3 * 512 + 9] = 0.0;
        let out = resample_by_surface(&img, &p.angle_grid(), &SurfaceRule::default(), None);
        for k in 0..img.len() {
            assert_eq!(out.range_m[k].to_bits(), img.range_m[k].to_bits(), "{k}");
            if img.is_valid(k) {
                assert_eq!(out.xyz[k], img.xyz[k]);
                assert_eq!(out.point_index[k], img.point_index[k]);
            } else {
                assert_eq!(out.point_index[k], NO_POINT);
            }
        }
    }

    /// Moves every return of `img` `fraction` of a column clockwise of its pixel's centre
    /// (its range kept), as a projected scan's nearest return lies anywhere in its pixel.
    fn measure_clockwise(img: &mut RangeImage, fraction: f32) {
        let shift = fraction * std::f32::consts::TAU / img.width as f32;
        for k in 0..img.len() {
            let (phi, theta) = (
                img.angles.elevation_rad[k],
                img.angles.azimuth_rad[k] - shift,
            );
            let d = img.range_m[k];
            img.xyz[k] = [
                d * phi.cos() * theta.cos(),
                d * phi.cos() * theta.sin(),
                d * phi.sin(),
            ];
        }
    }

    #[test]
    fn a_finer_azimuth_grid_keeps_each_return_where_it_was_measured() {
        // 8 x 128, each return measured 0.3 of a pixel clockwise of its pixel's centre, as a
        // projected scan's nearest return lies anywhere inside its pixel.
        let p = uniform_profile(8, 128, 7.0, -7.0);
        let mut img = smooth_image(&p);
        measure_clockwise(&mut img, 0.3);
        let fine = p.angle_grid().resized(8, 512);
        let out = resample_by_surface(&img, &fine, &SurfaceRule::default(), None);
        let bilinear = resample_image(&img, &fine, Interpolation::Bilinear);
        let mut blended = 0;
        for k in 0..img.len() {
            let [x, y, _] = img.xyz[k];
            let measured = y.atan2(x);
            let row = k / 128;
            let at = (0..512)
                .map(|c| row * 512 + c)
                .min_by(|&a, &b| {
                    angle_diff(fine.azimuth_rad[a], measured)
                        .total_cmp(&angle_diff(fine.azimuth_rad[b], measured))
                })
                .unwrap();
            assert_eq!(out.range_m[at].to_bits(), img.range_m[k].to_bits(), "{k}");
            assert_eq!((out.point_index[at], out.xyz[at]), (k as u32, img.xyz[k]));
            blended += usize::from(bilinear.range_m[at] != img.range_m[k]);
        }
        assert!(blended > img.len() / 2, "bilinear blends them: {blended}");
        // The pixels between measured returns are still filled.
        assert_eq!(out.valid_count(), bilinear.valid_count());
    }

    #[test]
    fn a_pixel_is_never_nearer_than_the_return_its_span_kept() {
        // A pole at 5 m before a wall at 30 m, every return measured 0.4 of a pixel clockwise
        // of its pixel's centre: the first finer pixels right of the pole lie closer to the
        // pole's return than to the wall's, but inside the wall's pixel, whose span held no
        // return nearer than the wall's (projection keeps the nearest).
        let p = uniform_profile(8, 128, 7.0, -7.0);
        let mut img = smooth_image(&p);
        for k in 0..img.len() {
            img.range_m[k] = if (40..44).contains(&(k % 128)) {
                5.0
            } else {
                30.0
            };
        }
        measure_clockwise(&mut img, 0.4);
        let fine = p.angle_grid().resized(8, 512);
        let out = resample_by_surface(&img, &fine, &SurfaceRule::default(), None);
        for k in 0..fine.len() {
            let own = (k / 512) * 128 + (k % 512) / 4;
            let floor = img.range_m[own] * (1.0 - 1e-5);
            assert!(out.range_m[k] >= floor, "{k}: {}", out.range_m[k]);
        }
        // The pole still fills the finer pixels of its own span next to its return.
        let row = 3 * 512;
        let near = |a: f32, b: f32| (a - b).abs() < 1e-3;
        assert!(near(out.range_m[row + 4 * 43 + 3], 5.0));
        assert!(near(out.range_m[row + 4 * 44], 30.0));
    }

    #[test]
    fn column_weights_follow_the_measured_azimuths() {
        // Returns of columns 3 and 4 measured 0.4 left of and 0.2 right of their centres
        // (in columns, so 1.6 columns apart): a target at 3.5 lies 0.9 / 1.6 of the way.
        let mut measured = vec![f32::NAN; 8];
        measured[3] = 2.6;
        measured[4] = 4.2;
        let s = column_share(&measured, 3, 4, 3, 3.5, 8);
        assert!((s - 0.9 / 1.6).abs() < 1e-5, "{s}");
        // Without a measured azimuth on both sides: the pixel centres.
        assert_eq!(column_share(&measured, 3, 5, 3, 3.25, 8), 0.25);
        // Across the seam (columns 7 and 0 of 8).
        measured[7] = 7.3;
        measured[0] = 7.9;
        let s = column_share(&measured, 7, 0, 7, 7.6, 8);
        assert!((s - 0.5).abs() < 1e-5, "{s}");
    }
}
