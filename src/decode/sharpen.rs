//! Sharpening a scan's ray-drop probability before masks are drawn from it.
//!
//! Drawing every pixel's drop independently from x_n spreads the drops of a smooth x_n over
//! whole surfaces: a wall where x_n is 0.1 comes out with one ray in ten missing, salt and
//! pepper, while a real wall loses almost none and the sky, glass and far ground lose most.
//! Sharpening keeps each scan's expected number of drops and moves them to where x_n is
//! highest: p' = sigmoid(s * logit(p) + b), with the offset b solved per scan so that the
//! mean of p' is the mean of p. s = 1 is the plain draw.

/// The drop probabilities `drop_prob` sharpened by `sharpness` (>= 1 concentrates, 1 leaves
/// them as they are), with the scan's mean drop probability kept.
pub fn sharpen_drop_prob(drop_prob: &[f32], sharpness: f32) -> Vec<f32> {
    if drop_prob.is_empty() || sharpness == 1.0 {
        return drop_prob.to_vec();
    }
    // Probabilities of exactly 0 or 1 (rows no model reaches) stay where they are.
    let logits: Vec<f64> = drop_prob
        .iter()
        .map(|p| {
            let p = f64::from(*p).clamp(1e-6, 1.0 - 1e-6);
            f64::from(sharpness) * (p / (1.0 - p)).ln()
        })
        .collect();
    let target = drop_prob.iter().map(|p| f64::from(*p)).sum::<f64>() / drop_prob.len() as f64;
    let mean_at = |b: f64| logits.iter().map(|l| sigmoid(l + b)).sum::<f64>() / logits.len() as f64;
    // The mean rises monotonically with b: bisect on it.
    let (mut lo, mut hi) = (-60.0, 60.0);
    for _ in 0..60 {
        let mid = 0.5 * (lo + hi);
        if mean_at(mid) < target {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    let b = 0.5 * (lo + hi);
    logits.iter().map(|l| sigmoid(l + b) as f32).collect()
}

fn sigmoid(x: f64) -> f64 {
    1.0 / (1.0 + (-x).exp())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sharpening_keeps_the_mean_and_moves_drops_to_the_likeliest_pixels() {
        let p: Vec<f32> = (0..1000).map(|i| 0.02 + 0.6 * (i as f32 / 999.0)).collect();
        let mean = |v: &[f32]| v.iter().map(|x| f64::from(*x)).sum::<f64>() / v.len() as f64;
        let s = sharpen_drop_prob(&p, 3.0);
        assert!(
            (mean(&s) - mean(&p)).abs() < 1e-4,
            "{} vs {}",
            mean(&s),
            mean(&p)
        );
        // Lower where x_n was low, higher where it was highest; the order is kept.
        assert!(
            s[0] < p[0] && s[999] > p[999],
            "{} {} {} {}",
            s[0],
            p[0],
            s[999],
            p[999]
        );
        assert!(s.windows(2).all(|w| w[0] <= w[1]));
        assert_eq!(sharpen_drop_prob(&p, 1.0), p);
    }
}
