//! A recording's own ray-drop rates: how often each pixel of a sensor's range image came back
//! empty over the recording's scans, and from that a drop probability for each scan fitted on
//! the *other* scans (leave one out), so a scan's rate never just copies its own mask.
//!
//! The rate of a pixel pools the columns around it in its row ([`DropCensus::window`]) and is
//! shrunk toward its row's rate by a prior weight of [`DropCensus::prior_scans`] scans: with
//! few scans the row's rate dominates, with many the pixel's own pattern (the vehicle's body,
//! the sky, a window that never returns) does.

use super::RangeImage;

/// Per-pixel counts of empty returns over a recording's scans on one grid.
#[derive(Debug, Clone, PartialEq)]
pub struct DropCensus {
    pub height: usize,
    pub width: usize,
    /// Scans counted.
    pub scans: u32,
    /// Per pixel (row-major): scans in which the pixel had no return.
    dropped: Vec<u32>,
    /// Columns on each side of a pixel pooled into its rate.
    pub window: usize,
    /// Weight of the row's rate, in scans' worth of the pixel's pooled counts.
    pub prior_scans: f32,
}

/// Columns on each side pooled into a pixel's rate and the row prior's weight (in scans):
/// chosen on the KITTI validation drive (`examples/raydrop_rates.rs`).
pub const DEFAULT_WINDOW: usize = 2;
pub const DEFAULT_PRIOR_SCANS: f32 = 2.0;

/// Rates are kept off 0 and 1 so that a log-likelihood stays finite.
const RATE_FLOOR: f32 = 1e-3;

fn dropped(d: f32) -> bool {
    !(d.is_finite() && d > 0.0)
}

impl DropCensus {
    pub fn new(height: usize, width: usize) -> Self {
        DropCensus {
            height,
            width,
            scans: 0,
            dropped: vec![0; height * width],
            window: DEFAULT_WINDOW,
            prior_scans: DEFAULT_PRIOR_SCANS,
        }
    }

    /// Whether `image` lies on this census's grid.
    pub fn fits(&self, image: &RangeImage) -> bool {
        image.height == self.height && image.width == self.width
    }

    /// Counts one scan; an image on another grid is ignored (returns false).
    pub fn add(&mut self, image: &RangeImage) -> bool {
        if !self.fits(image) {
            return false;
        }
        for (n, &d) in self.dropped.iter_mut().zip(&image.range_m) {
            *n += u32::from(dropped(d));
        }
        self.scans += 1;
        true
    }

    /// The drop probability of every pixel of `image`, fitted on the census's other scans:
    /// `image` is taken out of the counts when `counted` (it was added). `None` for an image
    /// on another grid, or when there is no other scan (see [`row_rates`]).
    pub fn rates_for(&self, image: &RangeImage, counted: bool) -> Option<Vec<f32>> {
        let others = self.scans.saturating_sub(u32::from(counted));
        if !self.fits(image) || self.width == 0 || others == 0 {
            return None;
        }
        let own: Vec<u32> = image
            .range_m
            .iter()
            .map(|&d| u32::from(dropped(d)))
            .collect();
        let (h, w) = (self.height, self.width);
        let counts: Vec<u32> = (0..h * w)
            .map(|k| self.dropped[k].saturating_sub(if counted { own[k] } else { 0 }))
            .collect();
        let window = self.window.min((w - 1) / 2);
        let pooled_n = others as f32 * (2 * window + 1) as f32;
        let mut out = vec![0.0f32; h * w];
        for r in 0..h {
            let row = &counts[r * w..(r + 1) * w];
            let row_total: u32 = row.iter().sum();
            let p_row = (row_total as f32 + 1.0) / (others as f32 * w as f32 + 2.0);
            let prior = self.prior_scans * (2 * window + 1) as f32;
            // A running sum over the circular window of columns.
            let mut sum: u32 = (0..=2 * window).map(|i| row[(w + i - window) % w]).sum();
            for c in 0..w {
                let p = (sum as f32 + prior * p_row) / (pooled_n + prior);
                out[r * w + c] = p.clamp(RATE_FLOOR, 1.0 - RATE_FLOOR);
                sum = sum + row[(c + window + 1) % w] - row[(w + c - window) % w];
            }
        }
        Some(out)
    }
}

/// Each row's share of empty pixels in one scan (`own`: 1 = dropped), for every pixel.
fn own_row_rates(own: &[u32], height: usize, width: usize) -> Vec<f32> {
    let mut out = Vec::with_capacity(height * width);
    for r in 0..height {
        let n: u32 = own[r * width..(r + 1) * width].iter().sum();
        let p = (n as f32 / width as f32).clamp(RATE_FLOOR, 1.0 - RATE_FLOOR);
        out.extend(std::iter::repeat_n(p, width));
    }
    out
}

/// Weight of the generator's x_n against the recording's own rates where both exist: each
/// pixel's drop probability is sigmoid(w logit(x_n) + (1 - w) logit(rate)), a product of the
/// two experts. Chosen on the KITTI validation drive (`examples/sensor_eval.rs`: NLL 0.369
/// for x_n alone, 0.257 for the rates alone, 0.251 at 0.15-0.25, 0.254 at 0.35).
pub const X_N_WEIGHT: f32 = 0.2;

/// `x_n` (drop probabilities) combined in place with `rates` as a product of experts, `weight`
/// on `x_n` ([`X_N_WEIGHT`]).
pub fn combine_with_rates(x_n: &mut [f32], rates: &[f32], weight: f32) {
    let logit = |p: f32| {
        let p = p.clamp(RATE_FLOOR, 1.0 - RATE_FLOOR);
        (p / (1.0 - p)).ln()
    };
    for (p, r) in x_n.iter_mut().zip(rates) {
        let l = weight * logit(*p) + (1.0 - weight) * logit(*r);
        *p = 1.0 / (1.0 + (-l).exp());
    }
}

/// Negative log-likelihood of one pixel's outcome (`dropped` or not) under drop probability `p`.
pub fn pixel_nll(p: f32, dropped: bool) -> f64 {
    let p = (p as f64).clamp(1e-6, 1.0 - 1e-6);
    if dropped { -p.ln() } else { -(1.0 - p).ln() }
}

/// Mean negative log-likelihood per pixel of `image`'s drops under `drop_prob`.
pub fn drop_nll(image: &RangeImage, drop_prob: &[f32]) -> f64 {
    let n = image.range_m.len().min(drop_prob.len());
    if n == 0 {
        return f64::NAN;
    }
    let total: f64 = (0..n)
        .map(|k| pixel_nll(drop_prob[k], dropped(image.range_m[k])))
        .sum();
    total / n as f64
}

/// Per-row drop rates of `image` itself (the baseline a drop model must beat).
pub fn row_rates(image: &RangeImage) -> Vec<f32> {
    let own: Vec<u32> = image
        .range_m
        .iter()
        .map(|&d| u32::from(dropped(d)))
        .collect();
    own_row_rates(&own, image.height, image.width)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lidar::SensorProfile;

    fn image(range: impl Fn(usize, usize) -> f32) -> RangeImage {
        let grid = SensorProfile::builtin("vlp16")
            .unwrap()
            .with_columns(64)
            .angle_grid();
        let mut img = RangeImage::empty(grid);
        for r in 0..img.height {
            for c in 0..img.width {
                img.range_m[r * img.width + c] = range(r, c);
            }
        }
        img
    }

    /// A body blocking columns 10-19 of the bottom rows in every scan, and random drops
    /// elsewhere: the census's rates find the body from the other scans, and beat each
    /// scan's own per-row rate there on a scan it did not count.
    #[test]
    fn the_census_learns_a_fixed_pattern_from_other_scans() {
        let mut rng = crate::util::rng::Rng::new(3);
        let mut scans = Vec::new();
        for _ in 0..20 {
            let mut draws = Vec::new();
            for _ in 0..16 * 64 {
                draws.push(rng.uniform());
            }
            scans.push(image(|r, c| {
                let body = r >= 12 && (10..20).contains(&c);
                if body || draws[r * 64 + c] < 0.1 {
                    0.0
                } else {
                    10.0
                }
            }));
        }
        let mut census = DropCensus::new(16, 64);
        for s in &scans[..19] {
            assert!(census.add(s));
        }
        let held_out = &scans[19];
        let rates = census.rates_for(held_out, false).unwrap();
        assert!(rates[13 * 64 + 15] > 0.8, "{}", rates[13 * 64 + 15]);
        assert!(rates[13 * 64 + 40] < 0.3, "{}", rates[13 * 64 + 40]);
        let ours = drop_nll(held_out, &rates);
        let rows = drop_nll(held_out, &row_rates(held_out));
        assert!(ours < 0.9 * rows, "census {ours} vs own rows {rows}");
        // Leaving a counted scan out gives the same rates as never counting it.
        census.add(held_out);
        assert_eq!(census.rates_for(held_out, true).unwrap(), rates);
    }

    #[test]
    fn one_scan_has_no_rates_of_others_and_other_grids_are_refused() {
        let scan = image(|r, c| if r == 0 && c < 32 { 0.0 } else { 5.0 });
        let mut census = DropCensus::new(16, 64);
        census.add(&scan);
        assert!(census.rates_for(&scan, true).is_none());
        let rates = row_rates(&scan);
        assert!((rates[0] - 0.5).abs() < 1e-6 && rates[64] == RATE_FLOOR);
        let other = RangeImage::empty(
            SensorProfile::builtin("vlp16")
                .unwrap()
                .with_columns(32)
                .angle_grid(),
        );
        assert!(census.rates_for(&other, false).is_none());
        assert!(!census.add(&other));
        // Combining keeps a probability between its experts' and leaves equal ones alone.
        let mut x_n = vec![0.9f32, 0.3];
        combine_with_rates(&mut x_n, &[0.1, 0.3], 0.5);
        assert!(
            (x_n[0] - 0.5).abs() < 1e-5 && (x_n[1] - 0.3).abs() < 1e-5,
            "{x_n:?}"
        );
        // A known-bad model (drops predicted where returns are) scores worse than the rows.
        let wrong: Vec<f32> = scan
            .range_m
            .iter()
            .map(|&d| if d > 0.0 { 0.9 } else { 0.1 })
            .collect();
        assert!(drop_nll(&scan, &wrong) > drop_nll(&scan, &rates));
    }
}
