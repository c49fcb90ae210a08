//! Deterministic randomness for the simulator and the physics layer.
//!
//! Every draw is a pure function of integer keys (scene seed, scan index, ray
//! index, a per-effect salt), so results never depend on thread scheduling or on
//! the order in which rays are processed. [`key_hash`] mixes keys with the
//! SplitMix64 finaliser; [`Rng`] is a small sequential stream (SplitMix64) for
//! scene generation, where draws happen in a fixed order on one thread.

/// SplitMix64 finaliser: a bijective 64-bit mix with full avalanche.
#[inline]
pub fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// Hash of an ordered list of keys.
#[inline]
pub fn key_hash(keys: &[u64]) -> u64 {
    let mut h = 0x9e37_79b9_7f4a_7c15u64;
    for &k in keys {
        h = mix64(h ^ k.wrapping_mul(0x9e37_79b9_7f4a_7c15));
    }
    h
}

/// A uniform draw in [0, 1) from a hash (24 high bits, exact in f32).
#[inline]
pub fn unit_f32(h: u64) -> f32 {
    (h >> 40) as f32 * (1.0 / (1u64 << 24) as f32)
}

/// A uniform draw in [0, 1) keyed by `keys`.
#[inline]
pub fn uniform(keys: &[u64]) -> f32 {
    unit_f32(key_hash(keys))
}

/// A standard normal draw keyed by `keys` (Box-Muller on two derived uniforms).
#[inline]
pub fn gaussian(keys: &[u64]) -> f32 {
    let h = key_hash(keys);
    let u1 = ((h >> 40) as f64 + 0.5) / (1u64 << 24) as f64;
    let u2 = ((h & 0xff_ffff) as f64) / (1u64 << 24) as f64;
    ((-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()) as f32
}

/// A sequential SplitMix64 stream, for single-threaded scene generation.
#[derive(Debug, Clone)]
pub struct Rng {
    state: u64,
}

impl Rng {
    pub fn new(seed: u64, stream: u64) -> Self {
        Rng {
            state: key_hash(&[seed, stream]),
        }
    }

    pub fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(0x9e37_79b9_7f4a_7c15);
        mix64(self.state)
    }

    /// Uniform in [0, 1).
    pub fn unit(&mut self) -> f32 {
        unit_f32(self.next_u64())
    }

    /// Uniform in [lo, hi).
    pub fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.unit()
    }

    /// True with probability `p`.
    pub fn chance(&mut self, p: f32) -> bool {
        self.unit() < p
    }

    /// Uniform integer in [0, n); 0 when n is 0.
    pub fn index(&mut self, n: usize) -> usize {
        if n == 0 {
            0
        } else {
            (self.next_u64() % n as u64) as usize
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn draws_depend_only_on_keys() {
        assert_eq!(uniform(&[1, 2, 3]), uniform(&[1, 2, 3]));
        assert_ne!(uniform(&[1, 2, 3]), uniform(&[1, 2, 4]));
        assert_ne!(uniform(&[1, 2, 3]), uniform(&[3, 2, 1]));
        let mut a = Rng::new(7, 1);
        let mut b = Rng::new(7, 1);
        assert_eq!(a.next_u64(), b.next_u64());
        assert_ne!(Rng::new(7, 2).next_u64(), Rng::new(7, 1).next_u64());
    }

    #[test]
    fn uniform_and_gaussian_have_the_right_moments() {
        let n = 100_000u64;
        let u: Vec<f32> = (0..n).map(|i| uniform(&[42, i])).collect();
        let mean = u.iter().sum::<f32>() / n as f32;
        assert!((mean - 0.5).abs() < 0.01, "{mean}");
        assert!(u.iter().all(|x| (0.0..1.0).contains(x)));
        let g: Vec<f32> = (0..n).map(|i| gaussian(&[42, i])).collect();
        let m = g.iter().sum::<f32>() / n as f32;
        let var = g.iter().map(|x| (x - m) * (x - m)).sum::<f32>() / n as f32;
        assert!(
            m.abs() < 0.02 && (var - 1.0).abs() < 0.03,
            "mean {m} var {var}"
        );
    }
}
