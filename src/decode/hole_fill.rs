//! A learned correction of the completed depth in dropped rays: a small network reads the
//! measured returns around a pixel whose ray came back empty (a window of its neighbours,
//! and the nearest return in each of eight directions with what the decoded scene x_d
//! renders there) relative to the completion's value, and moves that value along its ray.
//! The completion (a fill from the returns on the pixel's surface near them, x_d farther
//! in) cannot weigh which neighbours to trust, nor bend x_d's surface to the measured edge
//! of a hole; the pattern of returns and of x_d's error at the border often can. Trained on
//! KITTI training drives with holes of every [`HoleKind`](crate::lidar::holes::HoleKind)
//! cut into them ([`crate::train::hole_fill`]; `cargo run --release --example
//! hole_fill_fit` rebuilds the shipped `models/hole_fill.json`, built into the binary).
//!
//! Sensors no model covers get a second network of the same shape
//! (`models/hole_fill_prior_free.json`, `hole_fill_fit --prior-free`): it corrects the
//! completion without a prior and reads the line fill along rows and columns in x_d's place.
//! It is fitted on KITTI scans thinned to 64, 32 and 16 beams at 512 to 2048 columns, so that
//! it sees more than one beam spacing; [`crate::decode::prior_free`] checks it on each scan.

use std::path::Path;
use std::sync::OnceLock;

use anyhow::{Context, Result, bail};
use serde::{Deserialize, Serialize};

use super::row_fill::moved;
use crate::util::mlp::Mlp;

/// Steps from the nearest return within which a dropped ray of the model grid is filled
/// from the returns around it; farther in, the rendering x_d is the better guess (on the
/// validation drive: 3 beats 2, 4, 6 and 8 on large holes, within 1 % elsewhere).
pub const COMPLETION_REACH: u32 = 3;

/// What the network reads around a dropped pixel.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Window {
    /// Rows on each side of the pixel's own in the window of neighbours.
    pub half_rows: usize,
    /// Columns on each side.
    pub half_columns: usize,
    /// How many steps each of the eight directions is searched for a return.
    pub reach: usize,
}

/// The eight directions searched from a dropped pixel (rows, columns).
const DIRECTIONS: [(isize, isize); 8] = [
    (-1, 0),
    (1, 0),
    (0, -1),
    (0, 1),
    (-1, -1),
    (-1, 1),
    (1, -1),
    (1, 1),
];
/// Features per direction: found, steps, the return's log depth relative to the start, and
/// relative to x_d there.
const PER_DIRECTION: usize = 4;
/// Features of the pixel itself ([`push_features`]).
const OWN: usize = 5;
/// Log-depth ratios are clamped to this before they enter the network.
const MAX_RATIO: f32 = 3.0;

impl Window {
    fn neighbours(&self) -> usize {
        (2 * self.half_rows + 1) * (2 * self.half_columns + 1) - 1
    }

    /// Inputs per pixel: each neighbour's log depth relative to the start and whether it is
    /// there; per direction [`PER_DIRECTION`]; then the pixel's own.
    pub fn features(&self) -> usize {
        2 * self.neighbours() + DIRECTIONS.len() * PER_DIRECTION + OWN
    }
}

impl Default for Window {
    fn default() -> Self {
        Window {
            half_rows: 2,
            half_columns: 2,
            reach: 32,
        }
    }
}

/// The trained correction, as saved in `hole_fill.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct HoleFill {
    pub window: Window,
    pub net: Mlp,
}

impl HoleFill {
    /// The network shipped in `models/hole_fill.json`, built into the binary.
    pub fn shipped() -> &'static HoleFill {
        static SHIPPED: OnceLock<HoleFill> = OnceLock::new();
        Self::built_in(&SHIPPED, include_str!("../../models/hole_fill.json"))
    }

    /// The network for sensors no model covers, shipped in
    /// `models/hole_fill_prior_free.json`: it corrects the completion without a prior and
    /// reads the line fill where [`HoleFill::shipped`] reads x_d
    /// ([`crate::decode::prior_free::complete_without_prior`]).
    pub fn prior_free() -> &'static HoleFill {
        static SHIPPED: OnceLock<HoleFill> = OnceLock::new();
        Self::built_in(
            &SHIPPED,
            include_str!("../../models/hole_fill_prior_free.json"),
        )
    }

    fn built_in(cell: &'static OnceLock<HoleFill>, text: &str) -> &'static HoleFill {
        cell.get_or_init(|| {
            Self::parse(text).expect("the shipped hole fills are checked by a unit test")
        })
    }

    pub fn new(window: Window, net: Mlp) -> HoleFill {
        HoleFill { window, net }
    }

    pub fn load(path: &Path) -> Result<HoleFill> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("cannot read the hole fill '{}'", path.display()))?;
        Self::parse(&text).with_context(|| format!("'{}' is not a hole fill", path.display()))
    }

    fn parse(text: &str) -> Result<HoleFill> {
        let fill: HoleFill = serde_json::from_str(text)?;
        let w = fill.window;
        if w.half_rows > 8 || w.half_columns > 8 || !(1..=256).contains(&w.reach) {
            bail!("its window ({w:?}) is out of range");
        }
        let features = w.features();
        if !fill.net.takes(features, 1) {
            bail!(
                "its network takes {} inputs where its window gives {features}",
                fill.net.inputs()
            );
        }
        Ok(fill)
    }

    /// `completed` (the completion of `observed` on its grid, `height x width`, x_d far from
    /// returns) with every dropped pixel that has a return in two or more directions moved
    /// by the network; `distance` is each pixel's steps to the nearest return
    /// ([`crate::lidar::holes::distance_to_returns`] of `observed`). Measured returns and pixels the
    /// completion left at 0 stay as they are.
    pub fn refine(
        &self,
        images: (&[f32], &[f32], &[f32]),
        distance: &[u32],
        size: (usize, usize),
    ) -> Vec<f32> {
        self.refine_where(images, distance, size, |_| true)
    }

    /// [`HoleFill::refine`] of the dropped pixels in `wanted` only; the others as completed.
    pub fn refine_where(
        &self,
        (observed, completed, x_d): (&[f32], &[f32], &[f32]),
        distance: &[u32],
        size: (usize, usize),
        wanted: impl Fn(usize) -> bool,
    ) -> Vec<f32> {
        let images = (observed, completed, x_d);
        let dropped = dropped_features(self.window, images, distance, size, wanted);
        let moves = self.net.forward(&dropped.x);
        let mut out = completed.to_vec();
        for (&k, m) in dropped.pixels.iter().zip(moves) {
            out[k] = moved(completed[k], m);
        }
        out
    }
}

/// The dropped pixels the network moves and their features, [`Window::features`] each.
pub(crate) struct Dropped {
    pub pixels: Vec<usize>,
    pub x: Vec<f32>,
}

/// The images a dropped pixel's features are read from.
struct Images<'a> {
    observed: &'a [f32],
    completed: &'a [f32],
    x_d: &'a [f32],
    distance: &'a [u32],
    h: usize,
    w: usize,
}

impl Images<'_> {
    /// The pixel `(r + dr, c + dc)`, columns wrapping around; `None` past the first or last
    /// row.
    fn at(&self, r: usize, c: usize, dr: isize, dc: isize) -> Option<usize> {
        let row = usize::try_from(r as isize + dr)
            .ok()
            .filter(|&q| q < self.h)?;
        Some(row * self.w + (c as isize + dc).rem_euclid(self.w as isize) as usize)
    }
}

/// The features of every dropped pixel of `observed` in `wanted` that the network moves:
/// `completed` set there and a return in two or more directions.
pub(crate) fn dropped_features(
    window: Window,
    (observed, completed, x_d): (&[f32], &[f32], &[f32]),
    distance: &[u32],
    (h, w): (usize, usize),
    wanted: impl Fn(usize) -> bool,
) -> Dropped {
    let images = Images {
        observed,
        completed,
        x_d,
        distance,
        h,
        w,
    };
    let mut out = Dropped {
        pixels: Vec::new(),
        x: Vec::new(),
    };
    let mut found = Vec::with_capacity(DIRECTIONS.len());
    for k in 0..h * w {
        if observed[k] > 0.0 || completed[k] <= 0.0 || !wanted(k) {
            continue;
        }
        let (r, c) = (k / w, k % w);
        found.clear();
        found.extend(DIRECTIONS.iter().map(|&(dr, dc)| {
            (1..=window.reach as isize).find_map(|s| {
                let q = images.at(r, c, dr * s, dc * s)?;
                (observed[q] > 0.0).then_some((s, q))
            })
        }));
        if found.iter().flatten().count() < 2 {
            continue;
        }
        out.pixels.push(k);
        push_features(window, &images, (r, c), &found, &mut out.x);
    }
    out
}

fn push_features(
    window: Window,
    images: &Images,
    (r, c): (usize, usize),
    found: &[Option<(isize, usize)>],
    x: &mut Vec<f32>,
) {
    let k = r * images.w + c;
    let here = images.completed[k];
    let ratio = |d: f32, to: f32| (d / to).ln().clamp(-MAX_RATIO, MAX_RATIO);
    let (hr, hc) = (window.half_rows as isize, window.half_columns as isize);
    for dr in -hr..=hr {
        for dc in (-hc..=hc).filter(|&dc| dr != 0 || dc != 0) {
            let d = images.at(r, c, dr, dc).map_or(0.0, |q| images.observed[q]);
            let (v, m) = if d > 0.0 {
                (ratio(d, here), 1.0)
            } else {
                (0.0, 0.0)
            };
            x.extend([v, m]);
        }
    }
    for hit in found {
        match *hit {
            Some((steps, q)) => {
                let d = images.observed[q];
                let prior = images.x_d[q];
                let against_prior = if prior > 0.0 { ratio(d, prior) } else { 0.0 };
                x.extend([
                    1.0,
                    steps as f32 / window.reach as f32,
                    ratio(d, here),
                    against_prior,
                ]);
            }
            None => x.extend([0.0; PER_DIRECTION]),
        }
    }
    let own_prior = images.x_d[k];
    x.extend([
        if own_prior > 0.0 {
            ratio(own_prior, here)
        } else {
            0.0
        },
        here.ln() / 4.0,
        r as f32 / images.h as f32,
        (1.0 + images.distance[k].min(1000) as f32).ln() / 3.0,
        f32::from(u8::from(images.distance[k] <= COMPLETION_REACH)),
    ]);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lidar::holes;

    #[test]
    fn the_shipped_hole_fills_load_and_read_their_window() {
        for fill in [HoleFill::shipped(), HoleFill::prior_free()] {
            assert_eq!(fill.net.inputs(), fill.window.features());
        }
        let fill = HoleFill::shipped();
        let mut text = serde_json::to_value(fill).unwrap();
        text["window"]["half_columns"] = 3.into();
        let err = HoleFill::parse(&text.to_string()).unwrap_err();
        assert!(err.to_string().contains("inputs"), "{err}");
    }

    #[test]
    fn only_dropped_pixels_with_returns_around_them_move() {
        let (h, w) = (8, 16);
        let mut observed = vec![10.0; h * w];
        observed[3 * w + 5] = 0.0; // a dropped ray amid returns
        observed[..w].fill(0.0); // a top row with no return
        let mut completed = observed.clone();
        completed[3 * w + 5] = 10.0;
        let x_d = vec![12.0; h * w];
        let window = Window::default();
        let distance = holes::distance_to_returns(&observed, h, w);
        let images = (&observed[..], &completed[..], &x_d[..]);
        let d = dropped_features(window, images, &distance, (h, w), |_| true);
        assert_eq!(d.pixels, vec![3 * w + 5], "the top row was left at 0");
        assert_eq!(d.x.len(), window.features());
        // Every neighbour there, at the start's depth; x_d 12 m against 10 m.
        assert!(
            d.x[..2 * window.neighbours()]
                .chunks(2)
                .all(|p| p == [0.0, 1.0])
        );
        let own = &d.x[d.x.len() - OWN..];
        assert!((own[0] - (1.2f32).ln()).abs() < 1e-6);
        let out = HoleFill::shipped().refine(images, &distance, (h, w));
        assert_eq!(out[..3 * w + 5], completed[..3 * w + 5]);
        assert_eq!(out[3 * w + 6..], completed[3 * w + 6..]);
        assert!(
            (out[3 * w + 5] - 10.0).abs() < 1.0,
            "a flat wall stays flat: {}",
            out[3 * w + 5]
        );
    }
}
