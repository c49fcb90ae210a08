//! Gaps in a recording: sectors of a scan in which no row holds a return. Lost packets, a
//! recording that began or ended mid-revolution, or a driver that publishes a partial
//! frame leave whole columns empty; the catalogue's physics does not do that to every beam
//! of a column at once (a vehicle body blocks the bottom rows, the sky the top ones). Such
//! sectors are reported as gaps in the data and left out of every drop rate and fit, so
//! they are never read as self-occlusion. (An obstacle nearer than the minimum range in
//! front of every beam looks the same; the report says so.)

use serde::Serialize;

use super::features::ScanFeatures;

/// The narrowest sector counted as a gap: a column or two without any return can be a
/// real scene (a doorway into the dark), five degrees of them is missing data.
pub const MIN_GAP_DEG: f32 = 5.0;

/// One gap of one scan.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Gap {
    /// `sim` or `real`.
    pub recording: &'static str,
    /// The scan's index in its recording.
    pub scan: usize,
    /// The sector's first and last column's azimuth, degrees.
    pub azimuth_deg: (f32, f32),
    pub columns: usize,
}

impl Gap {
    pub fn sentence(&self) -> String {
        format!(
            "{} scan {}: azimuth {:.0} to {:.0} deg ({} columns) has no return in any row",
            self.recording, self.scan, self.azimuth_deg.0, self.azimuth_deg.1, self.columns
        )
    }
}

/// One sentence on all of `gaps` (the first few named), or `None` where there are none.
pub fn summary(gaps: &[Gap]) -> Option<String> {
    const NAMED: usize = 4;
    if gaps.is_empty() {
        return None;
    }
    let named: Vec<String> = gaps.iter().take(NAMED).map(Gap::sentence).collect();
    let more = gaps.len().saturating_sub(NAMED);
    Some(format!(
        "{} sectors without a return in any row are gaps in the data (lost packets, a revolution recorded in part, or something nearer than the sensor's minimum range in front of every beam), left out of every rate and fit rather than named as an effect: {}{}",
        gaps.len(),
        named.join("; "),
        if more > 0 {
            format!("; and {more} more")
        } else {
            String::new()
        }
    ))
}

/// What a user is told of the check on a recording of one scan.
pub const ONE_SCAN_CAVEAT: &str = "the real recording has one scan: the effects were fitted on half of its pixels (alternate cells of 2 beams by 1/64 of a revolution) and checked on the other half, which share its scene; a second scan gives a stronger check";

/// Cells of the checkerboard that splits one scan into a fit half and a held-out half: 2
/// beams by 1/64 of a revolution, so every beam and every sector has pixels in both.
const SPLIT_ROWS: usize = 2;
const SPLIT_SECTORS: usize = 64;

/// One scan as two: the pixels of alternate checkerboard cells left out of each (as gaps),
/// for a recording with a single scan, whose fit can only be checked on held-out pixels.
pub fn split_pixels(f: &ScanFeatures) -> (ScanFeatures, ScanFeatures) {
    let (h, w) = (f.height, f.width);
    let cell_w = (w / SPLIT_SECTORS).max(1);
    let half = |parity: usize| {
        let mut g = f.clone();
        g.gap = (0..h * w)
            .map(|k| f.in_gap(k) || ((k / w) / SPLIT_ROWS + (k % w) / cell_w) % 2 != parity)
            .collect();
        g
    };
    (half(0), half(1))
}

/// Runs of columns of `f` without a return in any row, at least `min_columns` long, as
/// `(first column, length)`; a run may wrap around the seam.
fn empty_runs(f: &ScanFeatures, min_columns: usize) -> Vec<(usize, usize)> {
    let (h, w) = (f.height, f.width);
    if w == 0 || f.len() != h * w {
        return Vec::new();
    }
    let empty: Vec<bool> = (0..w).map(|c| (0..h).all(|r| !f.kept[r * w + c])).collect();
    if empty.iter().all(|&e| e) {
        // A scan without any return is not a sector of one.
        return Vec::new();
    }
    // Start at a column with a return, so no run is split at the seam.
    let start = (0..w).find(|&c| !empty[c]).unwrap_or(0);
    let mut runs = Vec::new();
    let mut run: Option<(usize, usize)> = None;
    for i in 1..=w {
        let c = (start + i) % w;
        match (&mut run, empty[c]) {
            (Some((_, len)), true) => *len += 1,
            (None, true) => run = Some((c, 1)),
            (Some(r), false) => {
                if r.1 >= min_columns {
                    runs.push(*r);
                }
                run = None;
            }
            (None, false) => {}
        }
    }
    runs
}

/// The columns of `MIN_GAP_DEG` on a `width`-column grid (at least 2).
fn min_columns(width: usize) -> usize {
    ((width as f32 * MIN_GAP_DEG / 360.0).ceil() as usize).max(2)
}

/// Marks the gaps of `scans` (each pixel of a gap sector gets `gap` set) and lists them.
pub fn mark(scans: &mut [ScanFeatures], recording: &'static str) -> Vec<Gap> {
    let mut gaps = Vec::new();
    for (i, f) in scans.iter_mut().enumerate() {
        let runs = empty_runs(f, min_columns(f.width));
        if runs.is_empty() {
            continue;
        }
        let (h, w) = (f.height, f.width);
        let mut gap = vec![false; h * w];
        for &(first, len) in &runs {
            for j in 0..len {
                let c = (first + j) % w;
                (0..h).for_each(|r| gap[r * w + c] = true);
            }
            let azimuth = |c: usize| f.azimuth_rad[c].to_degrees();
            gaps.push(Gap {
                recording,
                scan: i,
                azimuth_deg: (azimuth(first), azimuth((first + len - 1) % w)),
                columns: len,
            });
        }
        f.gap = gap;
    }
    gaps
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A `h x w` scan, every pixel kept unless `dropped(row, column)`.
    fn scan(h: usize, w: usize, dropped: impl Fn(usize, usize) -> bool) -> ScanFeatures {
        let mut f = ScanFeatures::empty(h, w);
        for k in 0..h * w {
            f.kept.push(!dropped(k / w, k % w));
            f.azimuth_rad
                .push(std::f32::consts::PI - (k % w) as f32 * std::f32::consts::TAU / w as f32);
        }
        f
    }

    #[test]
    fn whole_empty_sectors_are_gaps_and_blocked_bottom_rows_are_not() {
        // 360 columns: a missing sector of 20 columns, a lone empty column, and the bottom
        // rows blocked (self-occlusion) over 60 columns.
        let f = scan(8, 360, |r, c| {
            (100..120).contains(&c) || c == 200 || (r >= 5 && c < 60)
        });
        let mut scans = vec![f];
        let gaps = mark(&mut scans, "real");
        assert_eq!(gaps.len(), 1, "{gaps:?}");
        assert_eq!(gaps[0].columns, 20);
        assert!((gaps[0].azimuth_deg.0 - 80.0).abs() < 0.5, "{gaps:?}");
        let f = &scans[0];
        assert!(f.in_gap(3 * 360 + 110) && !f.in_gap(3 * 360 + 200) && !f.in_gap(6 * 360 + 10));
    }

    #[test]
    fn one_scan_splits_into_halves_that_share_every_beam_and_sector() {
        let mut f = scan(8, 128, |_, c| (10..20).contains(&c));
        mark(std::slice::from_mut(&mut f), "real");
        let (a, b) = split_pixels(&f);
        for k in 0..f.len() {
            // A gap stays out of both; every other pixel is in exactly one half.
            assert_eq!(a.in_gap(k) && b.in_gap(k), f.in_gap(k), "pixel {k}");
        }
        for half in [&a, &b] {
            for r in 0..8 {
                assert!((0..128).any(|c| !half.in_gap(r * 128 + c)), "beam {r}");
            }
            for c in (30..128).step_by(2) {
                assert!((0..8).any(|r| !half.in_gap(r * 128 + c)), "column {c}");
            }
        }
    }

    #[test]
    fn a_gap_across_the_seam_is_one_gap_and_an_empty_scan_has_none() {
        let mut scans = vec![
            scan(4, 72, |_, c| !(6..66).contains(&c)),
            scan(4, 72, |_, _| true),
        ];
        let gaps = mark(&mut scans, "real");
        assert_eq!(gaps.len(), 1, "{gaps:?}");
        assert_eq!((gaps[0].scan, gaps[0].columns), (0, 12));
        assert!(scans[1].gap.is_empty());
    }
}
