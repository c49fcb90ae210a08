//! Decoding a scan through the spatial-latent model in one forward pass.
//!
//! The scan is encoded twice as one batch: each pass hides alternate stripes of
//! [`STRIPE`] columns (marks them unknown). A ray's x_d comes from the pass that saw it, its
//! drop probability x_n from the pass that did not, so x_n is what the model predicts from the
//! ray's surroundings, never a copy of whether the ray itself returned.

use burn::tensor::Device;
use burn::tensor::activation::sigmoid;

use super::{Observation, Queries, Ray, SpatialConfig, SpatialNet, encoder_input, grid_queries};
use crate::lidar::AngleGrid;
use crate::util::tensor::tensor_to_vec;

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

/// Decodes one scan: `rays` on `angles` (row-major).
pub fn decode(
    net: &SpatialNet,
    config: &SpatialConfig,
    rays: &[Ray],
    angles: &AngleGrid,
    device: &Device,
) -> Decoded {
    let (h, w) = (angles.height, angles.width);
    let mut inputs = Vec::new();
    let mut shape = [0, 0];
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
        let (x, s) = encoder_input(
            &Observation {
                rays: &hidden,
                angles,
            },
            config,
        );
        inputs.extend(x);
        shape = s;
    }
    let circular = wraps(angles);
    let latent = net.encode(inputs, 2, shape, circular, device);
    let queries = Queries::new(
        &grid_queries(angles),
        (shape[0] / 2, shape[1] / 2),
        circular,
        &config.renderer,
        device,
    );
    let out = net.render(latent, &queries);
    let log_depth = tensor_to_vec(out.log_depth);
    let keep = tensor_to_vec(sigmoid(out.keep_logit));
    let n = h * w;
    let mut depth_m = Vec::with_capacity(n);
    let mut drop_prob = Vec::with_capacity(n);
    for k in 0..n {
        let hidden_in = hiding_pass(k % w);
        let seen_in = 1 - hidden_in;
        depth_m.push(log_depth[seen_in * n + k].exp());
        drop_prob.push(1.0 - keep[hidden_in * n + k]);
    }
    Decoded { depth_m, drop_prob }
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

    #[test]
    fn drop_probability_never_sees_its_own_ray() {
        let device = Device::flex();
        let config = SpatialConfig::new();
        let net = config.init(&mut Rng::new(4), &device);
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
        let a = decode(&net, &config, &rays_of(&range), &angles, &device);
        assert_eq!(a.depth_m.len(), angles.len());
        assert!(a.depth_m.iter().all(|d| d.is_finite() && *d > 0.0));
        assert!(a.drop_prob.iter().all(|p| (0.0..=1.0).contains(p)));
        // Flip one ray between returned and dropped: its own x_n must not move, its x_d must.
        let k = 5 * angles.width + 17;
        let mut flipped = range.clone();
        flipped[k] = if range[k] > 0.0 { 0.0 } else { 12.0 };
        let b = decode(&net, &config, &rays_of(&flipped), &angles, &device);
        assert_eq!(a.drop_prob[k], b.drop_prob[k]);
        assert_ne!(a.depth_m[k], b.depth_m[k]);
    }
}
