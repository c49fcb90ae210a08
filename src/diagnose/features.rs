//! Per-pixel features for Sim2Real diagnosis, computed the same way on a
//! real or a simulated scan projected onto a [`RangeImage`].
//!
//! This module owns the cheap geometry that the drop-rate comparisons condition
//! on: a completion of dropped pixels (holes bridged along their surface, wide
//! holes near the ground completed as ground and walls, and a cheap neighbour
//! fill, or a completed depth given by the caller for the holes of the lower
//! half that no surface spans: the GAN's x_d, see `completion`), incidence
//! angles from the normals of the completed depth, depth-edge proximity, and
//! classes (labels where present, else the most common label among valid
//! neighbours). It does no statistics (see `stats`) and no I/O.

use crate::lidar::RangeImage;
use crate::lidar::edges::{EDGE_RELATIVE_JUMP, EdgeAxes, MAX_EDGE_PX, edge_proximity};
use crate::lidar::sweep::Seam;

/// Settings for [`ScanFeatures::from_image`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FeatureOptions {
    /// Neighbour-fill passes: a dropped pixel is completed if a valid pixel lies
    /// within this many 8-neighbour steps; farther ones stay without geometry.
    pub fill_passes: usize,
    /// A pixel is on a depth edge when a 4-neighbour's range differs from its own
    /// by more than this fraction of the nearer range.
    pub edge_relative_jump: f32,
    /// Edge proximity is counted in pixels up to this cap.
    pub max_edge_px: u8,
    /// Whether the columns wrap around (a full-turn scan).
    pub wrap_azimuth: bool,
    /// Longest run of dropped pixels along a row or column that [`bridge_fill`]
    /// spans between two returns of one surface.
    pub bridge_gap_px: usize,
}

impl Default for FeatureOptions {
    fn default() -> Self {
        FeatureOptions {
            fill_passes: 3,
            edge_relative_jump: EDGE_RELATIVE_JUMP,
            max_edge_px: MAX_EDGE_PX,
            wrap_azimuth: true,
            bridge_gap_px: 16,
        }
    }
}

/// Features of every pixel of one scan, row-major `H x W` (struct of arrays).
#[derive(Debug, Clone, PartialEq)]
pub struct ScanFeatures {
    pub height: usize,
    pub width: usize,
    /// Beam row of each pixel.
    pub row: Vec<u32>,
    /// Pixel azimuth, radians (reference convention of [`crate::lidar::AngleGrid`]).
    pub azimuth_rad: Vec<f32>,
    /// Pixel elevation, radians.
    pub elevation_rad: Vec<f32>,
    /// Measured range where kept, neighbour-filled range where dropped, NaN where
    /// no valid pixel was close enough to complete it.
    pub range_m: Vec<f32>,
    /// Angle between the ray and the completed surface normal, in [0, pi/2];
    /// NaN where the normal is undefined.
    pub incidence_rad: Vec<f32>,
    /// Unit normal of the measured surface in the sensor frame (from the returns alone, not
    /// the completion), facing the sensor; zero where it is undefined.
    pub normal: Vec<[f32; 3]>,
    /// Pixel distance to the nearest depth edge, capped at
    /// [`FeatureOptions::max_edge_px`]; the cap where no edge is near or no geometry.
    pub edge_px: Vec<u8>,
    /// The same along the row only ([`EdgeAxes::Row`]: object silhouettes, not far ground).
    pub row_edge_px: Vec<u8>,
    /// Semantic class (the low 16 bits of a SemanticKITTI label, the instance id
    /// dropped); 0 = unknown.
    pub class: Vec<u32>,
    /// Whether the pixel holds a return.
    pub kept: Vec<bool>,
    /// Whether the pixel lies in a gap of the recording ([`super::gaps`]): left out of
    /// every rate and fit. Empty: no gap.
    pub gap: Vec<bool>,
    /// Where the sweep starts, found from the cloud ([`Seam::find`]); `None`: KITTI's
    /// convention, straight ahead and counter-clockwise.
    pub seam: Option<Seam>,
}

impl ScanFeatures {
    /// No pixels yet, on an `height x width` grid (tests push their own pixels).
    #[cfg(test)]
    pub(crate) fn empty(height: usize, width: usize) -> Self {
        ScanFeatures {
            height,
            width,
            row: Vec::new(),
            azimuth_rad: Vec::new(),
            elevation_rad: Vec::new(),
            range_m: Vec::new(),
            incidence_rad: Vec::new(),
            normal: Vec::new(),
            edge_px: Vec::new(),
            row_edge_px: Vec::new(),
            class: Vec::new(),
            kept: Vec::new(),
            gap: Vec::new(),
            seam: None,
        }
    }

    pub fn len(&self) -> usize {
        self.kept.len()
    }

    pub fn is_empty(&self) -> bool {
        self.kept.is_empty()
    }

    /// Whether pixel `k` lies in a gap of the recording.
    pub fn in_gap(&self, k: usize) -> bool {
        self.gap.get(k).copied().unwrap_or(false)
    }

    /// Fraction of pixels without a return, outside the recording's gaps.
    pub fn drop_rate(&self) -> f64 {
        let counted = (0..self.len()).filter(|&k| !self.in_gap(k));
        let (n, dropped) = counted.fold((0usize, 0usize), |(n, d), k| {
            (n + 1, d + usize::from(!self.kept[k]))
        });
        dropped as f64 / n.max(1) as f64
    }

    /// Computes the features of a projected scan (neighbour-fill completion).
    pub fn from_image(image: &RangeImage, options: &FeatureOptions) -> Self {
        Self::from_image_completed(image, None, options)
    }

    /// Computes the features of a projected scan whose dropped pixels in the lower
    /// half of the image take their range from `completed` (row-major on the image's
    /// grid, meters; e.g. the GAN's x_d from auto-decoding) where it is positive and
    /// finite and no surface spans the hole. Everywhere else the neighbour fill stays:
    /// - a bridged hole keeps the geometry measured on both its sides; a guess that
    ///   disagrees with it would make every drop a depth edge with a grazing normal;
    /// - in the upper half a dropped ray mostly met nothing (sky, or beyond reach),
    ///   which a completion cannot say: it would put the sim's no-returns at the
    ///   model's typical depth, where the baseline would then expect real drops.
    ///
    /// Kept pixels keep their measured range; classes come from the neighbours.
    pub fn from_image_completed(
        image: &RangeImage,
        completed: Option<&[f32]>,
        options: &FeatureOptions,
    ) -> Self {
        let (h, w) = (image.height, image.width);
        let n = h * w;
        let kept: Vec<bool> = (0..n).map(|k| image.is_valid(k)).collect();
        let grid = Grid {
            h,
            w,
            wrap: options.wrap_azimuth,
        };
        let (mut range_m, class) = neighbour_fill(&grid, image, &kept, options.fill_passes);
        // Holes spanned by one surface get its geometry back, so their normals
        // (the incidence features) are not the flat patches a fill makes.
        let mut bridged = vec![false; n];
        for (k, r) in bridge_fill(&grid, image, &kept, options.bridge_gap_px)
            .into_iter()
            .enumerate()
        {
            if r.is_finite() {
                range_m[k] = r;
                bridged[k] = true;
            }
        }
        // Inside wide holes near the ground, where nothing bridges, the ground
        // and the walls standing on it are a better guess than a copied range.
        for (k, r) in ground_wall_fill(&grid, image, &kept)
            .into_iter()
            .enumerate()
        {
            if r.is_finite() && range_m[k].is_finite() && !bridged[k] {
                range_m[k] = r;
            }
        }
        if let Some(depth) = completed.filter(|d| d.len() == n) {
            for k in (h / 2) * w..n {
                let d = depth[k];
                if !kept[k] && !bridged[k] && d.is_finite() && d > 0.0 {
                    range_m[k] = d;
                }
            }
        }
        let dirs: Vec<[f32; 3]> = (0..n).map(|k| image.angles.direction(k)).collect();
        let incidence_rad = (normals(&grid, &range_m, &dirs).iter().zip(&dirs))
            .map(|(n, d)| {
                if *n == [0.0; 3] {
                    f32::NAN
                } else {
                    (-dot(*n, *d)).clamp(0.0, 1.0).acos()
                }
            })
            .collect();
        // The normals themselves from the returns alone: a fill beyond the last return of a
        // column (the far ground under the sky) would stand the ground up as a wall.
        let measured: Vec<f32> = (0..n)
            .map(|k| if kept[k] { image.range_m[k] } else { f32::NAN })
            .collect();
        let normal = normals(&grid, &measured, &dirs);
        let edges = |axes| {
            edge_proximity(
                &range_m,
                w,
                options.wrap_azimuth,
                axes,
                options.edge_relative_jump,
                options.max_edge_px,
            )
        };
        let (edge_px, row_edge_px) = (edges(EdgeAxes::Both), edges(EdgeAxes::Row));
        ScanFeatures {
            height: h,
            width: w,
            row: (0..n).map(|k| (k / w.max(1)) as u32).collect(),
            azimuth_rad: image.angles.azimuth_rad.clone(),
            elevation_rad: image.angles.elevation_rad.clone(),
            range_m,
            incidence_rad,
            normal,
            edge_px,
            row_edge_px,
            class,
            kept,
            gap: Vec::new(),
            seam: None,
        }
    }
}

/// Neighbour arithmetic on an `h x w` grid whose columns may wrap.
struct Grid {
    h: usize,
    w: usize,
    wrap: bool,
}

impl Grid {
    /// Pixel at offset (di, dj) from (i, j), if inside the grid.
    fn at(&self, i: usize, j: usize, di: isize, dj: isize) -> Option<usize> {
        let ii = i as isize + di;
        if ii < 0 || ii >= self.h as isize {
            return None;
        }
        let mut jj = j as isize + dj;
        if self.wrap {
            jj = jj.rem_euclid(self.w as isize);
        } else if jj < 0 || jj >= self.w as isize {
            return None;
        }
        Some(ii as usize * self.w + jj as usize)
    }
}

const EIGHT: [(isize, isize); 8] = [
    (-1, -1),
    (-1, 0),
    (-1, 1),
    (0, -1),
    (0, 1),
    (1, -1),
    (1, 0),
    (1, 1),
];

/// Completes dropped pixels pass by pass: each takes the mean range of its
/// already-known same-row neighbours, else of its known 8-neighbours (and the most
/// common nonzero label of the latter). Kept pixels keep their
/// own range and label, but an unlabelled kept pixel takes its neighbours' label.
fn neighbour_fill(
    grid: &Grid,
    image: &RangeImage,
    kept: &[bool],
    passes: usize,
) -> (Vec<f32>, Vec<u32>) {
    let n = kept.len();
    let mut range: Vec<f32> = (0..n)
        .map(|k| if kept[k] { image.range_m[k] } else { f32::NAN })
        .collect();
    let mut class: Vec<u32> = (0..n)
        .map(|k| if kept[k] { image.label[k] & 0xffff } else { 0 })
        .collect();
    for _ in 0..passes {
        let mut next_range = range.clone();
        let mut next_class = class.clone();
        let mut changed = false;
        for i in 0..grid.h {
            for j in 0..grid.w {
                let k = i * grid.w + j;
                let need_range = range[k].is_nan();
                if !need_range && class[k] != 0 {
                    continue;
                }
                let (mut sum, mut count) = (0.0f32, 0usize);
                let mut labels: Vec<u32> = Vec::new();
                for (di, dj) in EIGHT {
                    if let Some(m) = grid.at(i, j, di, dj)
                        && !range[m].is_nan()
                    {
                        sum += range[m];
                        count += 1;
                        if class[m] != 0 {
                            labels.push(class[m]);
                        }
                    }
                }
                if need_range && count > 0 {
                    // Same-row neighbours first: along a beam the range varies
                    // slowly on the ground, across beams it jumps.
                    let same_row: Vec<f32> = [-1isize, 1]
                        .iter()
                        .filter_map(|&dj| grid.at(i, j, 0, dj))
                        .map(|m| range[m])
                        .filter(|r| !r.is_nan())
                        .collect();
                    next_range[k] = if same_row.is_empty() {
                        sum / count as f32
                    } else {
                        same_row.iter().sum::<f32>() / same_row.len() as f32
                    };
                    changed = true;
                }
                if let Some(label) = most_common(&mut labels) {
                    next_class[k] = label;
                    changed = true;
                }
            }
        }
        range = next_range;
        class = next_class;
        if !changed {
            break;
        }
    }
    (range, class)
}

/// Largest disagreement, as a fraction of the inverse range, between a bridge and
/// the line through each end and its outer neighbour: beyond it the two ends lie
/// on different surfaces (or a curved one) and the hole is left to the fill.
const BRIDGE_TOLERANCE: f32 = 0.05;

/// Completes runs of dropped pixels that lie between two returns of one surface
/// along their row or column (at most `max_gap` pixels). Along a column the
/// inverse range of any plane is `a cos(elevation) + b sin(elevation)`, which the
/// two ends fix; along a row it is interpolated linearly in azimuth (exact on the
/// ground's rings, close on walls across small angles). Where both directions
/// bridge a pixel the shorter gap wins. NaN where nothing bridges.
fn bridge_fill(grid: &Grid, image: &RangeImage, kept: &[bool], max_gap: usize) -> Vec<f32> {
    let n = kept.len();
    let mut range = vec![f32::NAN; n];
    let mut gap = vec![usize::MAX; n];
    if max_gap == 0 || n == 0 {
        return range;
    }
    let inverse = |k: usize| 1.0 / image.range_m[k];
    type Interpolate = dyn Fn(f32, f32, f32, f32, f32) -> f32;
    let mut line = |pixels: &[usize], x: &dyn Fn(usize) -> f32, between: &Interpolate| {
        let mut last: Option<usize> = None;
        for (p, &k) in pixels.iter().enumerate() {
            if !kept[k] {
                continue;
            }
            if let Some(a) = last.filter(|&a| p - a > 1 && p - a - 1 <= max_gap) {
                let (ka, kb) = (pixels[a], k);
                let (xa, xb) = (x(a), x(p));
                let (ua, ub) = (inverse(ka), inverse(kb));
                let slope = (ub - ua) / (xb - xa);
                let outer = [
                    (a > 0 && kept[pixels[a - 1]])
                        .then(|| (ua - inverse(pixels[a - 1])) / (xa - x(a - 1))),
                    (p + 1 < pixels.len() && kept[pixels[p + 1]])
                        .then(|| (inverse(pixels[p + 1]) - ub) / (x(p + 1) - xb)),
                ];
                let allowed = BRIDGE_TOLERANCE * ua.max(ub);
                let one_surface = if outer.iter().all(Option::is_none) {
                    (ua - ub).abs() <= allowed
                } else {
                    outer
                        .iter()
                        .flatten()
                        .all(|s| ((s - slope) * (xb - xa)).abs() <= allowed)
                };
                if one_surface && slope.is_finite() {
                    let len = p - a - 1;
                    for (q, &m) in pixels.iter().enumerate().take(p).skip(a + 1) {
                        if len < gap[m] {
                            gap[m] = len;
                            range[m] = 1.0 / between(xa, ua, xb, ub, x(q));
                        }
                    }
                }
            }
            last = Some(p);
        }
    };
    let laps = if grid.wrap { 2 } else { 1 };
    for i in 0..grid.h {
        let pixels: Vec<usize> = (0..laps * grid.w)
            .map(|j| i * grid.w + j % grid.w)
            .collect();
        line(&pixels, &|p| p as f32, &|xa, ua, xb, ub, x| {
            ua + (ub - ua) * (x - xa) / (xb - xa)
        });
    }
    for j in 0..grid.w {
        let pixels: Vec<usize> = (0..grid.h).map(|i| i * grid.w + j).collect();
        line(
            &pixels,
            &|p| image.angles.elevation_rad[pixels[p]],
            &|xa, ua, xb, ub, x| (ua * (xb - x).sin() + ub * (x - xa).sin()) / (xb - xa).sin(),
        );
    }
    range
}

/// Returns below the sensor at least this far (m) may be ground.
const MIN_GROUND_DEPTH_M: f32 = 0.2;
/// A return lies on the ground when its height is within this share of the
/// ground's depth below the sensor (at least [`MIN_GROUND_DEPTH_M`]).
const GROUND_TOLERANCE: f32 = 0.15;

/// The ground's depth below the sensor: the 80th percentile over the bottom two
/// rows' returns below the sensor (the ground is the lowest surface; cars and
/// kerbs stand above it), None with fewer than 20 of them.
fn ground_depth_m(image: &RangeImage, kept: &[bool]) -> Option<f32> {
    let first = image.len().saturating_sub(2 * image.width);
    let mut depths: Vec<f32> = (first..image.len())
        .filter(|&k| kept[k])
        .map(|k| -image.range_m[k] * image.angles.elevation_rad[k].sin())
        .filter(|d| d.is_finite() && *d > MIN_GROUND_DEPTH_M)
        .collect();
    if depths.len() < 20 {
        return None;
    }
    let i = depths.len() * 4 / 5;
    Some(*depths.select_nth_unstable_by(i, f32::total_cmp).1)
}

/// Completes dropped rays below the horizon in a world of a level ground and
/// walls standing on it: a ray whose nearest return below it in its column lies
/// on the ground hits the ground at that return's depth, unless the nearest
/// return above it stands nearer than that ground point (then it hits that
/// wall). NaN where the column shows no ground below the ray, and where that
/// ground lies beyond the column's farthest return.
fn ground_wall_fill(grid: &Grid, image: &RangeImage, kept: &[bool]) -> Vec<f32> {
    let n = kept.len();
    let mut range = vec![f32::NAN; n];
    let Some(ground) = ground_depth_m(image, kept) else {
        return range;
    };
    let tolerance = (GROUND_TOLERANCE * ground).max(MIN_GROUND_DEPTH_M);
    let elevation = |k: usize| image.angles.elevation_rad[k];
    for j in 0..grid.w {
        let column: Vec<usize> = (0..grid.h).map(|i| i * grid.w + j).collect();
        // Nearest return above each pixel: (range, elevation).
        let mut above: Option<(f32, f32)> = None;
        let mut nearest_above = vec![None; grid.h];
        for (i, &k) in column.iter().enumerate() {
            nearest_above[i] = above;
            if kept[k] {
                above = Some((image.range_m[k], elevation(k)));
            }
        }
        // Beyond the column's farthest return the ground may have been out of
        // reach, which the fill must not decide.
        let farthest = column
            .iter()
            .filter(|&&k| kept[k])
            .map(|&k| image.range_m[k])
            .fold(0.0f32, f32::max);
        let mut below_depth: Option<f32> = None;
        for (i, &k) in column.iter().enumerate().rev() {
            if kept[k] {
                let depth = -image.range_m[k] * elevation(k).sin();
                below_depth = ((depth - ground).abs() <= tolerance).then_some(depth);
                continue;
            }
            let (Some(depth), e) = (below_depth, elevation(k)) else {
                continue;
            };
            if e >= 0.0 {
                continue;
            }
            let ground_r = depth / (-e).sin();
            let wall_r = nearest_above[i]
                .map(|(r, ea)| r * ea.cos() / e.cos())
                .filter(|&r| r < ground_r);
            if let Some(r) = wall_r.or((ground_r <= farthest).then_some(ground_r)) {
                range[k] = r;
            }
        }
    }
    range
}

/// The most frequent value (smallest on ties), or None for an empty slice.
fn most_common(values: &mut [u32]) -> Option<u32> {
    values.sort_unstable();
    let mut best: Option<(u32, usize)> = None;
    let mut i = 0;
    while i < values.len() {
        let mut j = i;
        while j < values.len() && values[j] == values[i] {
            j += 1;
        }
        if best.is_none_or(|(_, c)| j - i > c) {
            best = Some((values[i], j - i));
        }
        i = j;
    }
    best.map(|(v, _)| v)
}

fn sub(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn cross(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// Unit normals of the completed depth, facing the sensor (zero where undefined). Along each
/// image axis the tangent is the one-sided difference towards the neighbour with the smaller
/// range jump, so a normal does not straddle a depth edge.
fn normals(grid: &Grid, range: &[f32], dirs: &[[f32; 3]]) -> Vec<[f32; 3]> {
    let point = |k: usize| {
        let d = dirs[k];
        [range[k] * d[0], range[k] * d[1], range[k] * d[2]]
    };
    let tangent = |i: usize, j: usize, k: usize, axis: (isize, isize)| -> Option<[f32; 3]> {
        let fwd = grid
            .at(i, j, axis.0, axis.1)
            .filter(|&m| !range[m].is_nan());
        let back = grid
            .at(i, j, -axis.0, -axis.1)
            .filter(|&m| !range[m].is_nan());
        let jump = |m: usize| (range[m] - range[k]).abs();
        match (fwd, back) {
            (Some(f), Some(b)) if jump(f) <= jump(b) => Some(sub(point(f), point(k))),
            (Some(_), Some(b)) | (None, Some(b)) => Some(sub(point(k), point(b))),
            (Some(f), None) => Some(sub(point(f), point(k))),
            (None, None) => None,
        }
    };
    (0..range.len())
        .map(|k| {
            if range[k].is_nan() {
                return [0.0; 3];
            }
            let (i, j) = (k / grid.w, k % grid.w);
            let (Some(tu), Some(tv)) = (tangent(i, j, k, (0, 1)), tangent(i, j, k, (1, 0))) else {
                return [0.0; 3];
            };
            let normal = cross(tu, tv);
            let norm = dot(normal, normal).sqrt();
            if norm <= f32::EPSILON * range[k] * range[k] {
                return [0.0; 3];
            }
            let facing = if dot(normal, dirs[k]) > 0.0 {
                -1.0
            } else {
                1.0
            };
            normal.map(|c| c * facing / norm)
        })
        .collect()
}

/// Features of scans `0..scans` of a simulated drive (HDL-64E at 64 x 512) from
/// scene `seed` under `effects`: the fixture the diagnosis tests share.
#[cfg(test)]
pub(crate) fn simulated_recording(
    seed: u64,
    scans: u32,
    effects: Vec<Box<dyn crate::physics::Effect>>,
) -> Vec<ScanFeatures> {
    let profile = crate::lidar::SensorProfile::kitti_hdl64e().with_columns(512);
    simulated_recording_with(&profile, seed, scans, effects)
}

/// As [`simulated_recording`] with any sensor profile.
#[cfg(test)]
pub(crate) fn simulated_recording_with(
    profile: &crate::lidar::SensorProfile,
    seed: u64,
    scans: u32,
    effects: Vec<Box<dyn crate::physics::Effect>>,
) -> Vec<ScanFeatures> {
    simulated_images_with(profile, seed, scans, effects)
        .iter()
        .map(|img| ScanFeatures::from_image(img, &FeatureOptions::default()))
        .collect()
}

/// The range images behind [`simulated_recording_with`] (for other completions).
#[cfg(test)]
pub(crate) fn simulated_images_with(
    profile: &crate::lidar::SensorProfile,
    seed: u64,
    scans: u32,
    effects: Vec<Box<dyn crate::physics::Effect>>,
) -> Vec<RangeImage> {
    use crate::physics::Physics;
    use crate::sim::{SceneConfig, Simulator};
    // Scans 0.3 s apart: a short drive whose scene objects do not sit at the
    // same pixels in every scan (as they would in consecutive scans).
    const STRIDE: u32 = 3;
    let sim = Simulator::new(
        SceneConfig {
            seed,
            duration_s: 0.1 * (STRIDE * scans) as f32 + 0.1,
            ..Default::default()
        },
        profile.clone(),
    );
    let physics = Physics { effects };
    (0..scans)
        .map(|i| {
            let mut scan = sim.scan(STRIDE * i);
            physics.apply(&mut scan, seed);
            scan.image
        })
        .collect()
}

#[cfg(test)]
#[path = "features_tests.rs"]
mod tests;
