//! Samples for the learned hole fill ([`crate::decode::hole_fill`]): scans with holes of a
//! [`HoleKind`](crate::lidar::holes::HoleKind) cut into them, completed as `convert
//! --upsample-method guided` completes them (the guided fill near returns, x_d farther in),
//! and every cut pixel with a true return taken with its features, the completion there and
//! the true depth; fitted by [`super::ray_move`]. `examples/hole_fill_fit.rs` makes them from
//! KITTI training drives through the built binary, so that x_d is exactly what `convert`
//! renders (a drive's scans decoded in chains).

use super::ray_move::{Samples, pick};
use crate::decode::hole_fill::{Window, dropped_features};
use crate::lidar::holes;
use crate::util::rng::Rng;

/// One scan with holes cut into it, as `convert` completed it. Images are row-major
/// `height x width`, meters, 0 = no return.
pub struct Holed {
    pub height: usize,
    pub width: usize,
    /// The scan with the holes' returns removed.
    pub observed: Vec<f32>,
    /// `convert`'s completion of `observed` before the learned fill.
    pub completed: Vec<f32>,
    /// The second opinion the network reads beside the returns: the decoded scene's depth
    /// x_d, or without a prior the line fill ([`crate::decode::prior_free::prior_free_fills`]).
    pub x_d: Vec<f32>,
    /// The scan itself.
    pub truth: Vec<f32>,
    /// The pixels cut out.
    pub mask: Vec<bool>,
}

impl Holed {
    /// Up to `per_scan` of the cut pixels with a true return that the network would move
    /// (all of them when `per_scan` is `usize::MAX`), drawn with `rng`.
    pub fn samples(&self, window: Window, per_scan: usize, rng: &mut Rng) -> Samples {
        let size = (self.height, self.width);
        let (completed, truth) = (&self.completed, &self.truth);
        let distance = holes::distance_to_returns(&self.observed, size.0, size.1);
        let images = (&self.observed[..], &completed[..], &self.x_d[..]);
        let dropped = dropped_features(window, images, &distance, size, |_| true);
        let nf = window.features();
        let cut_with_truth = (0..dropped.pixels.len())
            .filter(|&i| {
                let k = dropped.pixels[i];
                self.mask[k] && truth[k] > 0.0
            })
            .collect();
        let order = pick(cut_with_truth, per_scan, rng);
        let mut out = Samples {
            features: nf,
            ..Samples::default()
        };
        for i in order {
            let k = dropped.pixels[i];
            out.push(&dropped.x[i * nf..(i + 1) * nf], completed[k], truth[k]);
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn samples_are_the_cut_pixels_with_a_true_return() {
        let (h, w) = (8, 16);
        let truth: Vec<f32> = (0..h * w)
            .map(|k| if k == 40 { 0.0 } else { 10.0 })
            .collect();
        let mut mask = vec![false; h * w];
        for k in [37, 38, 40] {
            mask[k] = true;
        }
        let observed: Vec<f32> = (0..h * w)
            .map(|k| if mask[k] { 0.0 } else { truth[k] })
            .collect();
        let holed = Holed {
            height: h,
            width: w,
            completed: vec![9.0; h * w],
            x_d: vec![11.0; h * w],
            observed,
            truth,
            mask,
        };
        let s = holed.samples(Window::default(), usize::MAX, &mut Rng::new(1));
        assert_eq!(s.len(), 2, "pixel 40 has no true return");
        assert_eq!(s.reference, vec![9.0, 9.0]);
        assert_eq!(s.truth, vec![10.0, 10.0]);
        assert_eq!(s.x.len(), 2 * Window::default().features());
        assert_eq!(
            holed.samples(Window::default(), 1, &mut Rng::new(1)).len(),
            1
        );
    }
}
