//! The completed depth of a scan no prior covers (`convert` on a sensor no model covers, or
//! `--prior-free`), and of a decoded scan on a grid much finer than its returns
//! ([`finer_than_returns`]): the scan's own returns filled edge-aware, then the learned hole
//! fill for sensors without a prior ([`HoleFill::prior_free`]) where a check on the scan
//! itself says it helps.
//!
//! The learned fill was fitted on KITTI thinned to other beam counts, and a sensor of
//! another make, or an indoor scene, may not behave like those. So it is checked on the
//! topic's own returns before it is trusted ([`FillCheck`], on the first scans of the topic
//! in the conversion's first pass): holes of three kinds (single rays, patches, whole beams)
//! are cut into the returns, a kind at a time, filled with and without the network, and for
//! each place a dropped ray can lie in ([`Place`]) the network's moves are kept only where
//! they came nearer the cut returns. The cuts are seeded from the scans, so the choice is
//! deterministic. Across an empty stretch of a column (an azimuth sector) the network is
//! never used.

use super::fill::Fill;
use super::hole_fill::HoleFill;
use crate::lidar::holes::{self, HoleKind};
use crate::lidar::line_fill::fill_along_lines;
use crate::lidar::{AngleGrid, RangeImage, ScatterFill, SurfaceRule, fill_scattered_in_angle};
use crate::util::rng::Rng;

/// The kinds of hole each scan checks the learned fill on, one for each place it decides
/// for: single rays (mostly [`Place::Beside`]), patches ([`Place::Inside`] and their rims)
/// and whole beams ([`Place::Between`]).
const PROBES: [HoleKind; 3] = [HoleKind::Pixels, HoleKind::Medium, HoleKind::Beams];
/// Cut returns of a place below which the check keeps the fill without the network.
const MIN_PROBED: usize = 30;

/// Where a dropped ray lies among the returns: the network's moves are kept or not for each.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Place {
    /// On a column with no return within the network's reach above or below (an azimuth
    /// sector without returns): never moved. The check cuts no sector (one would take a
    /// twelfth of the scan's returns), so nothing on the scan vouches for the network there.
    Across,
    /// On a row with no return within the network's reach on either side: a missing beam.
    Between,
    /// Next to a return (single dropped rays, the rim of a hole).
    Beside,
    /// Farther inside a hole.
    Inside,
}

impl Place {
    /// The places the check decides for.
    const CHECKED: [Place; 3] = [Place::Between, Place::Beside, Place::Inside];

    fn index(self) -> usize {
        self as usize
    }
}

/// The two fills of a scan no prior covers (`image`'s returns on its own grid): the
/// completion (measured returns kept, each dropped ray filled from the returns on its
/// surface around it, and where none is near (wide holes, sectors, missing beams) along its
/// row or column, [`fill_along_lines`]) and the line fill of every dropped ray, which the
/// learned hole fill reads where a prior would give it x_d.
pub fn prior_free_fills(image: &RangeImage) -> (Vec<f32>, Vec<f32>) {
    fills_where(image, |_| true, |_| true)
}

/// [`prior_free_fills`] of the dropped rays in `wanted` only (0 elsewhere), the line fill
/// only where the completion needs it and in `lines_too`.
fn fills_where(
    image: &RangeImage,
    wanted: impl Fn(usize) -> bool + Copy,
    lines_too: impl Fn(usize) -> bool,
) -> (Vec<f32>, Vec<f32>) {
    let how = ScatterFill::Surfaces {
        guide: None,
        guide_jump: SurfaceRule::default().guide_jump,
    };
    let local = fill_scattered_in_angle(&image.range_m, &image.angles, how, wanted);
    let lines = fill_along_lines(&image.range_m, &image.angles, |k| {
        wanted(k) && (local[k] <= 0.0 || lines_too(k))
    });
    let completed = (local.iter().zip(&lines))
        .map(|(&l, &f)| if l > 0.0 { l } else { f })
        .collect();
    (completed, lines)
}

/// The completed depth of a scan no prior covers: the completion of [`prior_free_fills`];
/// with [`Fill::Learned`], each dropped ray then moved by the learned fill in the places
/// where `check` found that it helps.
pub fn complete_without_prior(image: &RangeImage, fill: Fill, check: &FillCheck) -> Vec<f32> {
    if fill != Fill::Learned {
        return prior_free_fills(image).0;
    }
    let places = places(&image.range_m, (image.height, image.width));
    learned_completion(image, check, &places)
}

/// [`complete_without_prior`] written into `depth` (another completion of `image`'s grid)
/// everywhere but across azimuth sectors without returns ([`Place::Across`]), where `depth`
/// keeps its own: a decoded scene there knows more than the sector's two edges.
pub fn complete_without_prior_but_across(
    image: &RangeImage,
    fill: Fill,
    check: &FillCheck,
    depth: &mut [f32],
) {
    let places = places(&image.range_m, (image.height, image.width));
    let free = free_completion(image, fill, check, &places);
    for ((d, f), place) in depth.iter_mut().zip(free).zip(&places) {
        if *place != Some(Place::Across) {
            *d = f;
        }
    }
}

/// The completion of `image` without a prior: with [`Fill::Learned`] [`learned_completion`]
/// over its `places`, else the completion of [`prior_free_fills`].
fn free_completion(
    image: &RangeImage,
    fill: Fill,
    check: &FillCheck,
    places: &[Option<Place>],
) -> Vec<f32> {
    match fill {
        Fill::Learned => learned_completion(image, check, places),
        _ => prior_free_fills(image).0,
    }
}

/// The completion of every dropped ray, moved by the learned fill in the `places` where
/// `check` found that it helps.
fn learned_completion(image: &RangeImage, check: &FillCheck, places: &[Option<Place>]) -> Vec<f32> {
    let keep = check.keep();
    let moved = |k: usize| places[k].is_some_and(|p| keep[p.index()]);
    let (plain, learned) = both_fills(image, |_| true, moved);
    (0..plain.len())
        .map(|k| if moved(k) { learned[k] } else { plain[k] })
        .collect()
}

/// Below this share of returns followed by a return along the row ([`row_continuity`]) a
/// grid is finer than the scan's returns. KITTI scans: 0.90-0.91 on the grids their returns
/// fill (the 30 000-point drives at 512 columns, full scans at 2 048), 0.11 and 0 for the
/// 30 000-point drives at 1 024 and 2 048 columns.
const FILLED_ROWS: f64 = 0.5;

/// Whether `image`'s grid is much finer than its returns: most returns have an empty ray
/// next to them along the row, where a scan on a grid its returns fill has another return.
/// The decoded hole fill was fitted on grids the returns fill; on finer ones `convert` writes
/// the completion without a prior as `depth` ([`complete_without_prior`]).
pub fn finer_than_returns(image: &RangeImage) -> bool {
    row_continuity(image) < FILLED_ROWS
}

/// Beams this many times as far apart as the model's, or more, are too sparse for the
/// decoded hole fill (fitted on the model's own beams). On KITTI's validation drive with every
/// fourth beam kept (4x), it lost to interpolating the row on single rays, small, medium and
/// large holes, where the completion without a prior did not; with every second (2x) it lost
/// to neither.
const SPARSE_BEAMS: f32 = 3.0;

/// Whether the beams of `grid` are much farther apart than those of `model` (median spacing
/// of neighbouring rows, in elevation, [`SPARSE_BEAMS`] times or more): there `convert` writes
/// the completion without a prior as `depth`, but keeps the decoded one across azimuth sectors
/// without returns, where the prior knows more than the sector's two edges.
pub fn sparser_beams_than(grid: &AngleGrid, model: &AngleGrid) -> bool {
    let spacing = |g: &AngleGrid| {
        let mut steps: Vec<f32> = (1..g.height)
            .map(|r| (g.elevation_rad[r * g.width] - g.elevation_rad[(r - 1) * g.width]).abs())
            .collect();
        steps.sort_by(f32::total_cmp);
        steps.get(steps.len() / 2).copied()
    };
    match (spacing(grid), spacing(model)) {
        (Some(ours), Some(theirs)) => theirs > 0.0 && ours >= SPARSE_BEAMS * theirs,
        // A single beam is as sparse as a grid can be.
        (None, Some(_)) => true,
        _ => false,
    }
}

/// The share of `image`'s returns whose next ray along the row came back too: near 1 on a
/// grid the returns fill (gaps are drops), far below it on a grid finer than the returns.
pub fn row_continuity(image: &RangeImage) -> f64 {
    let w = image.width.max(1);
    let (mut returns, mut followed) = (0usize, 0usize);
    for row in image.range_m.chunks(w) {
        for j in 0..w {
            if row[j] > 0.0 {
                returns += 1;
                followed += usize::from(row[(j + 1) % w] > 0.0);
            }
        }
    }
    followed as f64 / returns.max(1) as f64
}

/// The completion (of the dropped rays in `wanted`) without and with the learned fill's
/// moves (of those in `moved`).
fn both_fills(
    image: &RangeImage,
    wanted: impl Fn(usize) -> bool + Copy,
    moved: impl Fn(usize) -> bool + Copy,
) -> (Vec<f32>, Vec<f32>) {
    let (plain, lines) = fills_where(image, wanted, moved);
    let size = (image.height, image.width);
    let distance = holes::distance_to_returns(&image.range_m, size.0, size.1);
    let images = (&image.range_m[..], &plain[..], &lines[..]);
    let learned = HoleFill::prior_free().refine_where(images, &distance, size, moved);
    (plain, learned)
}

/// The check of the learned fill on a topic's scans: per [`Place`], how many cut returns
/// were scored and how far the fill without and with the network missed them in all.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct FillCheck {
    scans: usize,
    sums: [(usize, f64, f64); 4],
}

impl FillCheck {
    /// A topic's scans the check runs on: its first, in file order. More cost a conversion
    /// three fills of each; one scan alone is noisy.
    pub const SCANS: usize = 4;

    /// The check on `image` alone, its holes drawn with `seed`.
    pub fn on(image: &RangeImage, seed: u64) -> FillCheck {
        let mut check = FillCheck::default();
        check.add(image, seed);
        check
    }

    /// The scans the check has run on.
    pub fn scans(&self) -> usize {
        self.scans
    }

    /// Adds `other`'s scans (an order-independent sum but for rounding: merge in file order).
    pub fn merge(&mut self, other: &FillCheck) {
        self.scans += other.scans;
        for (s, o) in self.sums.iter_mut().zip(&other.sums) {
            *s = (s.0 + o.0, s.1 + o.1, s.2 + o.2);
        }
    }

    /// Checks the fill on the returns of `image` cut out as holes of the [`PROBES`] kinds
    /// (drawn with `seed`), a kind at a time: holes of several kinds in one scan would leave
    /// the fill without the network fewer returns to work from than any one kind does.
    pub fn add(&mut self, image: &RangeImage, seed: u64) {
        let mut rng = Rng::new(seed);
        let (h, w) = (image.height, image.width);
        for kind in PROBES {
            let cut = kind.cut(&image.range_m, h, w, &mut rng);
            let mut probe = image.clone();
            for (d, &c) in probe.range_m.iter_mut().zip(&cut) {
                if c {
                    *d = 0.0;
                }
            }
            let (plain, learned) = both_fills(&probe, |k| cut[k], |k| cut[k]);
            let places = places(&probe.range_m, (h, w));
            for k in (0..h * w).filter(|&k| cut[k] && image.range_m[k] > 0.0) {
                let (Some(place), true) = (places[k], plain[k] > 0.0 && learned[k] > 0.0) else {
                    continue;
                };
                let truth = image.range_m[k];
                let s = &mut self.sums[place.index()];
                s.0 += 1;
                s.1 += f64::from((plain[k] - truth).abs());
                s.2 += f64::from((learned[k] - truth).abs());
            }
        }
        self.scans += 1;
    }

    /// For each [`Place`] (by [`Place::index`]), whether the learned fill came nearer the cut
    /// returns than the fill without it, over at least [`MIN_PROBED`] of them; never for
    /// [`Place::Across`].
    pub fn keep(&self) -> [bool; 4] {
        let mut keep = [false; 4];
        for p in Place::CHECKED {
            let (n, without, with) = self.sums[p.index()];
            keep[p.index()] = n >= MIN_PROBED && with < without;
        }
        keep
    }
}

/// The [`Place`] of every dropped ray of `observed` (`height x width`); `None` on returns.
pub fn places(observed: &[f32], (h, w): (usize, usize)) -> Vec<Option<Place>> {
    let reach = HoleFill::prior_free().window.reach;
    let distance = holes::distance_to_returns(observed, h, w);
    let row_gap = steps_along_rows(observed, h, w);
    let column_gap = steps_along_columns(observed, h, w);
    (0..h * w)
        .map(|k| {
            if observed[k] > 0.0 {
                None
            } else if column_gap[k] > reach {
                Some(Place::Across)
            } else if row_gap[k] > reach {
                Some(Place::Between)
            } else if distance[k] <= 1 {
                Some(Place::Beside)
            } else {
                Some(Place::Inside)
            }
        })
        .collect()
}

/// Columns from every pixel to the nearest return on its own row (columns wrap around);
/// `usize::MAX` on a row without one.
fn steps_along_rows(observed: &[f32], h: usize, w: usize) -> Vec<usize> {
    let mut out = vec![usize::MAX; h * w];
    for (row, steps) in observed.chunks(w).zip(out.chunks_mut(w)).take(h) {
        let hits: Vec<usize> = (0..w).filter(|&j| row[j] > 0.0).collect();
        if hits.is_empty() {
            continue;
        }
        for (j, s) in steps.iter_mut().enumerate() {
            let after = hits.partition_point(|&x| x < j);
            let next = hits[after % hits.len()];
            let before = hits[(after + hits.len() - 1) % hits.len()];
            *s = ((next + w - j) % w).min((j + w - before) % w);
        }
    }
    out
}

/// Rows from every pixel to the nearest return in its own column; `usize::MAX` on a column
/// without one.
fn steps_along_columns(observed: &[f32], h: usize, w: usize) -> Vec<usize> {
    let mut out = vec![usize::MAX; h * w];
    for j in 0..w {
        let mut last = None;
        for i in 0..h {
            if observed[i * w + j] > 0.0 {
                last = Some(i);
            }
            out[i * w + j] = last.map_or(usize::MAX, |l| i - l);
        }
        last = None;
        for i in (0..h).rev() {
            if observed[i * w + j] > 0.0 {
                last = Some(i);
            }
            let below = last.map_or(usize::MAX, |l| l - i);
            out[i * w + j] = out[i * w + j].min(below);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lidar::SensorProfile;

    #[test]
    fn places_tell_missing_beams_from_rims_and_insides() {
        let (h, w) = (8, 64);
        let mut observed = vec![10.0f32; h * w];
        observed[2 * w..3 * w].fill(0.0); // a missing beam
        for i in 4..7 {
            observed[i * w + 10..i * w + 15].fill(0.0); // a 3 x 5 hole
        }
        for i in 0..h {
            observed[i * w + 40] = 0.0; // a sector of one column
        }
        let p = places(&observed, (h, w));
        assert!(
            p[2 * w..3 * w]
                .iter()
                .all(|&x| x == Some(Place::Between) || x == Some(Place::Across))
        );
        assert_eq!(p[2 * w + 40], Some(Place::Across));
        assert_eq!(p[5 * w + 40], Some(Place::Across));
        assert_eq!(p[4 * w + 10], Some(Place::Beside));
        assert_eq!(p[5 * w + 12], Some(Place::Inside));
        assert_eq!(p[0], None);
        assert_eq!(steps_along_rows(&observed, h, w)[5 * w + 12], 3);
        assert_eq!(steps_along_columns(&observed, h, w)[5 * w + 12], 2);
    }

    #[test]
    fn a_grid_is_finer_than_returns_that_fill_one_ray_in_four() {
        let mut image = scene();
        assert!(row_continuity(&image) > 0.9, "{}", row_continuity(&image));
        assert!(!finer_than_returns(&image));
        // Scattered drops leave most returns beside another.
        for k in (0..image.range_m.len()).step_by(7) {
            image.range_m[k] = 0.0;
        }
        assert!(!finer_than_returns(&image));
        // The same returns on a grid four times finer: three rays in four empty.
        for (k, d) in image.range_m.iter_mut().enumerate() {
            if k % 4 != 0 {
                *d = 0.0;
            }
        }
        assert_eq!(row_continuity(&image), 0.0);
        assert!(finer_than_returns(&image));
        image.range_m.fill(0.0);
        assert!(finer_than_returns(&image), "a scan without returns");
    }

    #[test]
    fn every_fourth_beam_of_the_model_is_sparse_and_every_second_is_not() {
        let model = SensorProfile::kitti_hdl64e().with_columns(512);
        let every = |step: usize| {
            let mut p = model.clone();
            p.elevation_deg = p.elevation_deg.into_iter().step_by(step).collect();
            p.angle_grid()
        };
        let model = model.angle_grid();
        assert!(!sparser_beams_than(&model, &model));
        assert!(!sparser_beams_than(&every(2), &model));
        assert!(sparser_beams_than(&every(4), &model));
        assert!(sparser_beams_than(&every(64), &model), "one beam");
    }

    /// A sloped street of walls at 5-40 m on the VLP-16's grid.
    fn scene() -> RangeImage {
        let profile = SensorProfile::builtin("vlp16").unwrap().with_columns(720);
        let mut image = RangeImage::empty(profile.angle_grid());
        let w = image.width;
        for (k, d) in image.range_m.iter_mut().enumerate() {
            let (i, j) = (k / w, k % w);
            *d = 5.0 + 35.0 * ((j as f32 * 0.05).sin().abs()) + i as f32 * 0.1;
        }
        image
    }

    #[test]
    fn the_check_is_seeded_and_the_completion_keeps_every_return() {
        let mut image = scene();
        let w = image.width;
        image.range_m[3 * w..4 * w].fill(0.0);
        image.range_m[5 * w + 100] = 0.0;
        let check = FillCheck::on(&image, 7);
        assert_eq!(check, FillCheck::on(&image, 7));
        let mut four = FillCheck::default();
        (0..4).for_each(|_| four.merge(&check));
        assert_eq!((check.scans(), four.scans()), (1, 4));
        assert_eq!(
            four.keep(),
            check.keep(),
            "the same scan four times decides the same"
        );
        let a = complete_without_prior(&image, Fill::Learned, &check);
        for (k, &d) in image.range_m.iter().enumerate() {
            if d > 0.0 {
                assert_eq!(a[k], d, "a return keeps its depth");
            } else {
                assert!(a[k] > 0.0, "dropped ray {k} is filled");
            }
        }
        let plain = complete_without_prior(&image, Fill::Guided, &check);
        assert_eq!(plain, prior_free_fills(&image).0);
    }

    #[test]
    fn scans_without_returns_or_with_one_beam_complete_without_a_panic() {
        let mut empty = scene();
        empty.range_m.fill(0.0);
        let check = FillCheck::on(&empty, 3);
        assert_eq!(
            check.keep(),
            [false; 4],
            "nothing to check on, nothing kept"
        );
        let out = complete_without_prior(&empty, Fill::Learned, &check);
        assert!(out.iter().all(|&d| d == 0.0));
        let mut profile = SensorProfile::builtin("vlp16").unwrap().with_columns(90);
        profile.elevation_deg = vec![0.0];
        let mut one = RangeImage::empty(profile.angle_grid());
        one.range_m = (0..90)
            .map(|j| if j % 7 == 0 { 0.0 } else { 8.0 })
            .collect();
        let out = complete_without_prior(&one, Fill::Learned, &FillCheck::on(&one, 3));
        assert!((0..90).all(|j| out[j] > 0.0 && (j % 7 == 0 || out[j] == 8.0)));
    }
}
