//! Where a spinning sensor's sweep starts and which way it turns, read from one cloud: the
//! seam, where the last fired column meets the first. A sensor that moves during the sweep
//! shows its motion there (the two sides were measured a sweep apart), so the seam is found
//! from the data, not assumed: from the points' firing times where the cloud has a time
//! field, else from the order the points were written in (drivers write them in firing
//! order, organized or not). Clouds whose points are in no firing order have no seam.

use super::range_image::{NO_POINT, column_azimuth};
use super::{RangeImage, Scan};

/// The seam of one scan on its range image.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Seam {
    /// The image column fired first.
    pub first_column: usize,
    /// Whether the sweep runs towards higher image columns (clockwise seen from above:
    /// image columns run from azimuth +180 deg down to -180 deg).
    pub towards_higher_columns: bool,
    /// Per row, the columns of its returns fired first and last where they meet, where
    /// the row's own order shows them near the scan's seam: beams fire at azimuths of
    /// their own (an HDL-64E's or an Ouster's offsets reach a few degrees), and dropped
    /// rays at the seam part a row's meeting returns. Empty: every row meets at the seam.
    pub rows: Vec<Option<(usize, usize)>>,
}

/// How far (a share of the columns) a row's own meeting point may lie from the scan's
/// seam and still be taken as the row's.
const ROW_REACH: f64 = 1.0 / 32.0;

/// Share of a row's neighbouring returns whose firing order must agree with the sweep's
/// direction for the row to vote.
const MIN_ORDERED: f64 = 0.8;

impl Seam {
    /// KITTI's HDL-64E: the sweep starts straight ahead and turns counter-clockwise (the
    /// cameras are triggered as it passes the front).
    pub fn straight_ahead(width: usize) -> Seam {
        Seam {
            first_column: (width / 2).saturating_sub(1),
            towards_higher_columns: false,
            rows: Vec::new(),
        }
    }

    /// Row `row`'s first and last fired columns where they meet: its own, or the scan's.
    pub fn meeting(&self, row: usize, width: usize) -> (usize, usize) {
        match self.rows.get(row) {
            Some(Some(pair)) => *pair,
            _ => (self.first_column, self.last_column(width)),
        }
    }

    /// The image column fired last, beside the first.
    pub fn last_column(&self, width: usize) -> usize {
        if self.towards_higher_columns {
            (self.first_column + width - 1) % width
        } else {
            (self.first_column + 1) % width
        }
    }

    /// The azimuth between the last and the first fired column, radians.
    pub fn azimuth_rad(&self, width: usize) -> f32 {
        let a = column_azimuth(self.first_column, width);
        let b = column_azimuth(self.last_column(width), width);
        let mid = a + super::profile::wrap_pi(b - a) / 2.0;
        super::profile::wrap_pi(mid)
    }

    /// Whether the sweep turns counter-clockwise seen from above.
    pub fn counter_clockwise(&self) -> bool {
        !self.towards_higher_columns
    }

    /// The seam of `image`, projected from `scan`: each row votes for the column where the
    /// firing order of its returns starts over, and the rows must agree. `None` where the
    /// cloud's order says nothing (shuffled points, equal times, too few returns).
    pub fn find(scan: &Scan, image: &RangeImage) -> Option<Seam> {
        let times = scan
            .time_s
            .as_ref()
            .filter(|t| t.len() == scan.len())
            .filter(|t| spread(t) > 0.0);
        let key = |point: u32| -> f64 {
            match times {
                Some(t) => f64::from(t[point as usize]),
                None => f64::from(point),
            }
        };
        let (h, w) = (image.height, image.width);
        let per_row: Vec<Option<RowVote>> = (0..h)
            .map(|row| {
                let keys: Vec<(usize, f64)> = (0..w)
                    .filter(|&j| image.point_index[row * w + j] != NO_POINT)
                    .map(|j| (j, key(image.point_index[row * w + j])))
                    .collect();
                row_vote(&keys, w)
            })
            .collect();
        let votes: Vec<(usize, bool)> = per_row
            .iter()
            .flatten()
            .map(|v| (v.first, v.towards_higher))
            .collect();
        let mut seam = agree(&votes, w)?;
        let reach = row_reach(w);
        seam.rows = (per_row.iter())
            .map(|v| {
                let v = v
                    .as_ref()
                    .filter(|v| v.towards_higher == seam.towards_higher_columns)?;
                let d = (v.first + w - seam.first_column) % w;
                (d.min(w - d) <= reach).then_some((v.first, v.last))
            })
            .collect();
        Some(seam)
    }
}

/// One row's reading of the seam.
struct RowVote {
    first: usize,
    last: usize,
    towards_higher: bool,
}

fn spread(t: &[f32]) -> f32 {
    let (lo, hi) = t
        .iter()
        .filter(|v| v.is_finite())
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(a, b), &v| {
            (a.min(v), b.max(v))
        });
    if hi > lo { hi - lo } else { 0.0 }
}

/// One row's seam from its returns' firing keys in image-column order: the sweep's
/// direction (the way most neighbouring keys grow), and the two returns either side of the
/// largest step back against it. `None` where the row's order is not a sweep.
fn row_vote(keys: &[(usize, f64)], width: usize) -> Option<RowVote> {
    let n = keys.len();
    if n < 8.max(width / 8) {
        return None;
    }
    let step = |i: usize| keys[(i + 1) % n].1 - keys[i].1;
    let rising = (0..n).filter(|&i| step(i) > 0.0).count();
    let falling = (0..n).filter(|&i| step(i) < 0.0).count();
    let towards_higher = rising >= falling;
    if (rising.max(falling) as f64) < MIN_ORDERED * n as f64 {
        return None;
    }
    // The wrap: the one big step against the direction (`i` to `i + 1`, cyclically).
    let back = |i: usize| if towards_higher { -step(i) } else { step(i) };
    let wrap = (0..n).max_by(|&a, &b| back(a).total_cmp(&back(b)))?;
    let (a, b) = (keys[wrap].0, keys[(wrap + 1) % n].0);
    let (first, last) = if towards_higher { (b, a) } else { (a, b) };
    Some(RowVote {
        first,
        last,
        towards_higher,
    })
}

/// The seam most rows vote for: the direction of the majority, and the column with the
/// most votes within [`ROW_REACH`] of it (beams with azimuth offsets meet some columns apart),
/// which must hold half the rows that voted.
fn agree(votes: &[(usize, bool)], width: usize) -> Option<Seam> {
    if votes.is_empty() {
        return None;
    }
    let higher = votes.iter().filter(|v| v.1).count();
    let towards_higher = 2 * higher >= votes.len();
    let reach = row_reach(width);
    let near = |c: usize| {
        votes
            .iter()
            .filter(|v| v.1 == towards_higher)
            .filter(|v| {
                let d = (v.0 + width - c) % width;
                d.min(width - d) <= reach
            })
            .count()
    };
    let (column, count) = votes
        .iter()
        .filter(|v| v.1 == towards_higher)
        .map(|v| (v.0, near(v.0)))
        .max_by_key(|&(c, n)| (n, std::cmp::Reverse(c)))?;
    (2 * count >= votes.len()).then_some(Seam {
        first_column: column,
        towards_higher_columns: towards_higher,
        rows: Vec::new(),
    })
}

/// [`ROW_REACH`] in columns of a `width`-column grid.
fn row_reach(width: usize) -> usize {
    ((width as f64 * ROW_REACH).ceil() as usize).max(2)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lidar::{SensorProfile, Strategy, project};

    /// A ring of walls around a 16-beam sensor, its points in firing order from azimuth
    /// `start` (radians), turning `ccw` or not; with a time field or not.
    fn sweep(start: f32, ccw: bool, timed: bool, organized: bool) -> (Scan, RangeImage) {
        let profile = SensorProfile::builtin("vlp16").unwrap().with_columns(360);
        let columns = 360;
        let mut xyz = Vec::new();
        let mut time = Vec::new();
        let mut ring = Vec::new();
        // Organized: beams x columns; else column by column (the beams fastest).
        for c in 0..columns {
            let turned = (c as f32 + 0.5) / columns as f32 * std::f32::consts::TAU;
            let a = if ccw { start + turned } else { start - turned };
            for (b, e) in profile.elevation_deg.iter().enumerate() {
                let (e, r) = (e.to_radians(), 10.0 + (c % 7) as f32);
                xyz.push([r * e.cos() * a.cos(), r * e.cos() * a.sin(), r * e.sin()]);
                time.push(c as f32 * 1e-4);
                ring.push(b as u16);
            }
        }
        let mut scan = Scan::from_xyz(xyz);
        if organized {
            // Row-major: reorder to beams x columns.
            let beams = profile.beams();
            let order: Vec<usize> = (0..beams)
                .flat_map(|b| (0..columns).map(move |c| c * beams + b))
                .collect();
            scan.xyz = order.iter().map(|&k| scan.xyz[k]).collect();
            time = order.iter().map(|&k| time[k]).collect();
            ring = order.iter().map(|&k| ring[k]).collect();
            scan.height = beams;
            scan.width = columns;
        }
        scan.ring = Some(ring);
        if timed {
            scan.time_s = Some(time);
        }
        let image = project(&scan, &profile, Strategy::RingField).unwrap();
        (scan, image)
    }

    #[test]
    fn the_seam_is_where_the_firing_order_starts_over() {
        for (start_deg, ccw) in [
            (0.0f32, true),
            (180.0, false),
            (30.0, false),
            (-150.0, true),
        ] {
            for (timed, organized) in [(true, false), (false, false), (false, true)] {
                let (scan, image) = sweep(start_deg.to_radians(), ccw, timed, organized);
                let seam = Seam::find(&scan, &image).expect("a seam");
                assert_eq!(seam.counter_clockwise(), ccw, "{start_deg} {ccw}");
                let found = seam.azimuth_rad(image.width).to_degrees();
                let off = (found - start_deg + 540.0).rem_euclid(360.0) - 180.0;
                assert!(off.abs() < 1.5, "start {start_deg}: found {found}");
            }
        }
    }

    #[test]
    fn kitti_convention_and_no_order_give_what_they_should() {
        let seam = Seam::straight_ahead(512);
        assert!(seam.counter_clockwise());
        assert!(seam.azimuth_rad(512).abs() < 1e-3);
        assert_eq!(seam.last_column(512), 256);
        // Shuffled points, no time field: no seam.
        let (mut scan, _) = sweep(0.0, true, false, false);
        let mut rng = crate::util::rng::Rng::new(5);
        for i in (1..scan.len()).rev() {
            let j = rng.below(i + 1);
            scan.xyz.swap(i, j);
            scan.ring.as_mut().unwrap().swap(i, j);
        }
        let profile = SensorProfile::builtin("vlp16").unwrap().with_columns(360);
        let image = project(&scan, &profile, Strategy::RingField).unwrap();
        assert_eq!(Seam::find(&scan, &image), None);
    }
}
