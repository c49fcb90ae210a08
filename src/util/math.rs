//! Scalar functions shared by the likelihoods.

/// `ln(1 + e^x)`, stable for large |x| (`-ln sigmoid(-x)`).
pub fn softplus(x: f64) -> f64 {
    x.max(0.0) + (-x.abs()).exp().ln_1p()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn softplus_matches_the_naive_form_and_stays_finite() {
        for x in [-30.0, -2.0, 0.0, 1.5, 30.0] {
            assert!((softplus(x) - (1.0 + f64::exp(x)).ln()).abs() < 1e-12);
        }
        assert_eq!(softplus(1000.0), 1000.0);
        assert_eq!(softplus(-1000.0), 0.0);
    }
}
