//! Decoding a scan through the spatial-latent model in one forward pass.
//!
//! The scan is encoded twice as one batch: each pass hides alternate stripes of
//! [`STRIPE`] columns (marks them unknown). A ray's x_d comes from the pass that saw it, its
//! drop probability x_n from the pass that did not, so x_n is what the model predicts from the
//! ray's surroundings, never a copy of whether the ray itself returned.
//!
//! Both run on the host ([`super::host_encoder`], [`super::host`]), prepared once per model
//! ([`HostModel`]) and once per grid ([`GridQueries`]).

use super::host::{HostQueries, HostRenderer};
use super::host_encoder::HostEncoder;
use super::{
    OWN_FEATURES, Observation, Query, RAY_FEATURES, Ray, SpatialConfig, SpatialNet,
    base_log_depths, encoder_input, grid_queries, own_features,
};
use crate::lidar::AngleGrid;
use crate::lidar::range_image::azimuth_column;

/// A trained model prepared for decoding on the host: its config, encoder and renderer.
#[derive(Debug, Clone)]
pub struct HostModel {
    pub config: SpatialConfig,
    encoder: HostEncoder,
    renderer: HostRenderer,
}

impl HostModel {
    pub fn new(net: &SpatialNet, config: &SpatialConfig) -> Self {
        HostModel {
            config: config.clone(),
            encoder: HostEncoder::from_net(&net.encoder),
            renderer: HostRenderer::from_net(&net.renderer, config.encoder.latent),
        }
    }
}

/// Columns per hidden stripe of the two passes.
pub const STRIPE: usize = 4;

/// Which of the two passes hides column `j`.
pub fn hiding_pass(j: usize) -> usize {
    (j / STRIPE) % 2
}

/// The model's view of a scan on its own grid, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct Decoded {
    /// Depth x_d in metres at every ray (the model's surface, also where nothing returned).
    pub depth_m: Vec<f32>,
    /// Ray-drop probability x_n at every ray.
    pub drop_prob: Vec<f32>,
}

/// Whether a grid is a whole turn the encoder can wrap around: its columns must divide by the
/// encoder's multiple, since padding would put a seam into the turn.
pub fn wraps(angles: &AngleGrid) -> bool {
    angles.width.is_multiple_of(super::MULTIPLE)
}

/// A scan encoded by both passes: the latent grids `[2, latent, H'/2, W'/2]`, on the host.
pub struct Encoded {
    latent: Vec<f32>,
    /// What each pass showed of every ray of the observed grid, `[2, H W, OWN_FEATURES]`.
    own: Vec<f32>,
    /// The log depth each pass's rendering of each ray corrects, `[2, H W]`.
    base: Vec<f32>,
}

/// Encodes one scan: `rays` on `angles` (row-major), each pass hiding its stripes.
pub fn encode(model: &HostModel, rays: &[Ray], angles: &AngleGrid) -> Encoded {
    let config = &model.config;
    let w = angles.width;
    let circular = wraps(angles);
    let mut latent = Vec::new();
    let mut own = Vec::with_capacity(2 * rays.len() * OWN_FEATURES);
    for pass in 0..2 {
        let hidden: Vec<Ray> = rays
            .iter()
            .enumerate()
            .map(|(k, &r)| {
                if hiding_pass(k % w) == pass {
                    Ray::Unknown
                } else {
                    r
                }
            })
            .collect();
        let features = own_features(
            &Observation {
                rays: &hidden,
                angles,
                circular,
            },
            config,
        );
        let (x, shape) = encoder_input(&features, angles);
        latent.extend(model.encoder.forward(&x, shape, circular));
        own.extend(features);
    }
    Encoded {
        latent,
        base: base_log_depths(&own),
        own,
    }
}

/// Decodes one scan on its own grid.
pub fn decode(model: &HostModel, rays: &[Ray], angles: &AngleGrid) -> Decoded {
    let encoded = encode(model, rays, angles);
    render(model, &encoded, &own_queries(model, angles))
}

/// Where a grid's pixels are read from an encoding, prepared once per grid: the placed
/// queries (their Fourier features are the costly part), the nearest source column of each
/// (which pass saw it) and which pixels lie within the source's beams.
pub struct GridQueries {
    queries: HostQueries,
    columns: Vec<usize>,
    outside: Vec<usize>,
    /// For queries between the observed rays: the two source rays (the rows above and below
    /// at the nearest column) whose prior each query blends, with their weights. `None`: the
    /// queries are the observed grid's own rays, in order.
    between: Option<Vec<[(usize, f32); 2]>>,
}

/// The latent grid an observation on `grid` is encoded to: (rows, columns) of cells, and
/// whether it wraps around.
fn cells_of(grid: &AngleGrid) -> ((usize, usize), bool) {
    let (h, w) = (grid.height, grid.width);
    let cells = (
        h.next_multiple_of(super::MULTIPLE) / 2,
        w.next_multiple_of(super::MULTIPLE) / 2,
    );
    (cells, wraps(grid))
}

/// The queries of a scan's own grid, pixel for pixel.
pub fn own_queries(model: &HostModel, grid: &AngleGrid) -> GridQueries {
    let config = &model.config;
    let (cells, circular) = cells_of(grid);
    GridQueries {
        queries: HostQueries::new(
            &grid_queries(grid),
            cells,
            circular,
            &config.renderer,
            &model.renderer,
        ),
        columns: (0..grid.len()).map(|k| k % grid.width).collect(),
        outside: Vec::new(),
        between: None,
    }
}

/// The queries of another grid (denser, or another sensor's) read from scans on `source`.
/// Pixels more than [`OUTSIDE_RAD`] above or below the source's beams get depth 0 and drop
/// probability 1: the scan says nothing of them.
pub fn onto_queries(model: &HostModel, source: &AngleGrid, target: &AngleGrid) -> GridQueries {
    let rows = row_elevations(source);
    let mut queries = Vec::with_capacity(target.len());
    let mut columns = Vec::with_capacity(target.len());
    let mut between = Vec::with_capacity(target.len());
    let mut outside = Vec::new();
    for k in 0..target.len() {
        let (phi, theta) = (target.elevation_rad[k], target.azimuth_rad[k]);
        let (row, within) = row_of(&rows, phi);
        let col = azimuth_column(theta, source.width);
        queries.push(Query {
            row: super::pixel_to_cell(row),
            col: super::pixel_to_cell(col),
            elevation: phi,
            azimuth: theta,
        });
        let column = (col.round() as usize) % source.width.max(1);
        columns.push(column);
        let last = rows.len().saturating_sub(1);
        let above = (row.floor().max(0.0) as usize).min(last);
        let below = (above + 1).min(last);
        let t = (row - above as f32).clamp(0.0, 1.0);
        let ray = |i: usize| i * source.width + column;
        between.push([(ray(above), 1.0 - t), (ray(below), t)]);
        if !within {
            outside.push(k);
        }
    }
    let (cells, circular) = cells_of(source);
    GridQueries {
        queries: HostQueries::new(
            &queries,
            cells,
            circular,
            &model.config.renderer,
            &model.renderer,
        ),
        columns,
        outside,
        between: Some(between),
    }
}

/// Renders an encoded scan at prepared queries.
pub fn render(model: &HostModel, encoded: &Encoded, at: &GridQueries) -> Decoded {
    let mut out = render_queries(&model.renderer, encoded, at);
    for &k in &at.outside {
        out.depth_m[k] = 0.0;
        out.drop_prob[k] = 1.0;
    }
    out
}

/// How far outside its beams (radians) a scan is still rendered: 1 degree.
pub const OUTSIDE_RAD: f32 = std::f32::consts::PI / 180.0;

/// The mean elevation of each row of a grid, top first.
fn row_elevations(grid: &AngleGrid) -> Vec<f32> {
    (0..grid.height)
        .map(|i| {
            let row = &grid.elevation_rad[i * grid.width..(i + 1) * grid.width];
            row.iter().sum::<f32>() / row.len().max(1) as f32
        })
        .collect()
}

/// The fractional row at elevation `phi` on rows whose elevations fall from the top, and
/// whether it lies within [`OUTSIDE_RAD`] of them.
fn row_of(rows: &[f32], phi: f32) -> (f32, bool) {
    let n = rows.len();
    if n < 2 {
        return (0.0, n == 1 && (rows[0] - phi).abs() <= OUTSIDE_RAD);
    }
    let within = phi <= rows[0] + OUTSIDE_RAD && phi >= rows[n - 1] - OUTSIDE_RAD;
    // The segment [i, i + 1] that holds phi (the end segments extend outwards).
    let i = rows.windows(2).position(|p| phi >= p[1]).unwrap_or(n - 2);
    let (a, b) = (rows[i], rows[i + 1]);
    let t = if (a - b).abs() > 1e-9 {
        (a - phi) / (a - b)
    } else {
        0.0
    };
    (i as f32 + t, within)
}

/// Renders the queries of `at` from both passes; each query takes x_d from the pass that saw
/// its nearest column and x_n from the pass that hid it.
fn render_queries(host: &HostRenderer, encoded: &Encoded, at: &GridQueries) -> Decoded {
    let n = at.queries.len();
    let per_pass = encoded.latent.len() / 2;
    let rays = encoded.base.len() / 2;
    let passes: Vec<_> = (0..2)
        .map(|p| {
            let latent = &encoded.latent[p * per_pass..(p + 1) * per_pass];
            let own = &encoded.own[p * rays * OWN_FEATURES..(p + 1) * rays * OWN_FEATURES];
            let base = &encoded.base[p * rays..(p + 1) * rays];
            match &at.between {
                None => host.render(latent, &at.queries, own, base),
                Some(between) => {
                    let own = blend_priors(own, between);
                    host.render(latent, &at.queries, &own, &base_log_depths(&own))
                }
            }
        })
        .collect();
    let mut depth_m = Vec::with_capacity(n);
    let mut drop_prob = Vec::with_capacity(n);
    for (k, &c) in at.columns.iter().enumerate() {
        let hidden_in = hiding_pass(c);
        let seen_in = 1 - hidden_in;
        depth_m.push(passes[seen_in].log_depth[k].exp());
        let keep = 1.0 / (1.0 + (-passes[hidden_in].keep_logit[k]).exp());
        drop_prob.push(1.0 - keep);
    }
    Decoded { depth_m, drop_prob }
}

/// What queries between the observed rays are shown: unknown rays, with the prior blended
/// from the two source rays of each.
fn blend_priors(own: &[f32], between: &[[(usize, f32); 2]]) -> Vec<f32> {
    let mut out = vec![0.0f32; between.len() * OWN_FEATURES];
    for (q, pair) in between.iter().enumerate() {
        let dst = &mut out[q * OWN_FEATURES + RAY_FEATURES..(q + 1) * OWN_FEATURES];
        for &(k, weight) in pair {
            let src = &own[k * OWN_FEATURES + RAY_FEATURES..(k + 1) * OWN_FEATURES];
            for (d, s) in dst.iter_mut().zip(src) {
                *d += weight * s;
            }
        }
    }
    out
}

/// Each beam's drop rate among the rays of a scan that were fired and seen (returns and
/// drops; unknown rays do not count), with one pseudo-count each way.
pub fn row_drop_rates(rays: &[Ray], width: usize) -> Vec<f32> {
    rays.chunks(width.max(1))
        .map(|row| {
            let dropped = row.iter().filter(|r| matches!(r, Ray::Dropped)).count();
            let seen = row.iter().filter(|r| !matches!(r, Ray::Unknown)).count();
            (dropped as f32 + 1.0) / (seen as f32 + 2.0)
        })
        .collect()
}

/// x_n blended with the scan's own per-beam drop rates ([`row_drop_rates`]): `weight` on x_n.
/// Where x_n alone loses to the beam's rate (measured on the validation recordings, which
/// chose the model's [`SpatialConfig::x_n_weight`]) the blend keeps the better of both.
pub fn blend_with_row_rates(drop_prob: &mut [f32], rays: &[Ray], width: usize, weight: f32) {
    if weight >= 1.0 {
        return;
    }
    let rates = row_drop_rates(rays, width);
    for (k, p) in drop_prob.iter_mut().enumerate() {
        *p = weight * *p + (1.0 - weight) * rates[k / width.max(1)];
    }
}

/// The weights of x_n against the scan's own per-beam rates a scan chooses among.
pub const CHECKED_WEIGHTS: [f32; 5] = [1.0, 0.75, 0.5, 0.25, 0.0];

/// A per-scan check of x_n: the weight of [`CHECKED_WEIGHTS`] (at most `max_weight`) whose
/// blend with the scan's own per-beam rates explains the scan's own returns and drops best
/// (mean Bernoulli NLL over its fired rays). Each ray's x_n was rendered without seeing the
/// ray, so this is a held-out check; on a sensor or place where x_n loses to the scan's own
/// rates, the rates take over.
pub fn checked_weight(drop_prob: &[f32], rays: &[Ray], width: usize, max_weight: f32) -> f32 {
    let nll = |weight: f32| {
        let mut p = drop_prob.to_vec();
        blend_with_row_rates(&mut p, rays, width, weight);
        let (mut sum, mut n) = (0.0f64, 0usize);
        for (q, r) in p.iter().zip(rays) {
            let keep = f64::from(1.0 - q).clamp(1e-4, 1.0 - 1e-4);
            match r {
                Ray::Return(_) => sum -= keep.ln(),
                Ray::Dropped => sum -= (1.0 - keep).ln(),
                Ray::Unknown => continue,
            }
            n += 1;
        }
        sum / n.max(1) as f64
    };
    CHECKED_WEIGHTS
        .into_iter()
        .filter(|&w| w <= max_weight)
        .map(|w| (w, nll(w)))
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .map_or(0.0, |(w, _)| w)
}

/// The rays of a range image (`range_m`, 0 or not finite = no return), every ray fired.
pub fn rays_of(range_m: &[f32]) -> Vec<Ray> {
    range_m
        .iter()
        .map(|&r| {
            if r.is_finite() && r > 0.0 {
                Ray::Return(r)
            } else {
                Ray::Dropped
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lidar::SensorProfile;
    use crate::util::rng::Rng;
    use burn::tensor::Device;

    #[test]
    fn drop_probability_never_sees_its_own_ray() {
        let device = Device::flex();
        let config = SpatialConfig::new();
        let net = config.init_for_test(&mut Rng::new(4), &device);
        let angles = SensorProfile::builtin("vlp16")
            .expect("vlp16")
            .with_columns(64)
            .angle_grid();
        let mut rng = Rng::new(9);
        let range: Vec<f32> = (0..angles.len())
            .map(|_| {
                if rng.chance(0.8) {
                    rng.range(2.0, 40.0)
                } else {
                    0.0
                }
            })
            .collect();
        let model = HostModel::new(&net, &config);
        let a = decode(&model, &rays_of(&range), &angles);
        assert_eq!(a.depth_m.len(), angles.len());
        assert!(a.depth_m.iter().all(|d| d.is_finite() && *d > 0.0));
        assert!(a.drop_prob.iter().all(|p| (0.0..=1.0).contains(p)));
        // Flip one ray between returned and dropped: its own x_n must not move, its x_d must.
        let k = 5 * angles.width + 17;
        let mut flipped = range.clone();
        flipped[k] = if range[k] > 0.0 { 0.0 } else { 12.0 };
        let b = decode(&model, &rays_of(&flipped), &angles);
        assert_eq!(a.drop_prob[k], b.drop_prob[k]);
        assert_ne!(a.depth_m[k], b.depth_m[k]);
    }

    #[test]
    fn other_grids_render_like_the_own_grid_and_leave_other_beams_out() {
        let device = Device::flex();
        let config = SpatialConfig::new();
        let net = config.init_for_test(&mut Rng::new(4), &device);
        let angles = SensorProfile::builtin("vlp16")
            .expect("vlp16")
            .with_columns(64)
            .angle_grid();
        // Unknown rays: the own grid then reads nothing of its own rays either.
        let rays = vec![Ray::Unknown; angles.len()];
        let model = HostModel::new(&net, &config);
        let own = decode(&model, &rays, &angles);
        let encoded = encode(&model, &rays, &angles);
        let onto =
            |target: &AngleGrid| render(&model, &encoded, &onto_queries(&model, &angles, target));
        let again = onto(&angles);
        for k in 0..angles.len() {
            assert!((own.depth_m[k] - again.depth_m[k]).abs() < 1e-3 * own.depth_m[k]);
        }
        // An OS0's +-45 deg: beams beyond the VLP-16's +-15 deg are not rendered.
        let wide = SensorProfile::builtin("os0-32")
            .expect("os0")
            .with_columns(64)
            .angle_grid();
        let out = onto(&wide);
        assert_eq!(out.depth_m[0], 0.0);
        assert_eq!(out.drop_prob[0], 1.0);
        let middle = (wide.height / 2) * wide.width;
        assert!(out.depth_m[middle] > 0.0);
    }
}
