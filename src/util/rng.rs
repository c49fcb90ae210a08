//! Deterministic random numbers, the same on every thread count and backend.
//!
//! Two kinds: keyed draws ([`key_hash`], [`uniform`], [`gaussian`]), a pure function of
//! integer keys (scene seed, scan, ray, a per-effect salt), for work spread over threads in
//! any order; and [`Rng`], a sequential SplitMix64 stream whose whole state is one `u64` (so
//! a training run checkpoints it exactly), for draws made in a fixed order on one thread.
//! Drawn on the host, so every burn backend sees the same values for the same seed.

use burn::tensor::{Device, Tensor};
use serde::{Deserialize, Serialize};

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

/// SplitMix64: tiny, fast, and its whole state is one `u64` (easy to checkpoint).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq, Eq)]
pub struct Rng {
    state: u64,
}

impl Rng {
    pub fn new(seed: u64) -> Self {
        // Scramble once so that nearby seeds give unrelated streams.
        let mut rng = Self {
            state: seed ^ 0x9E37_79B9_7F4A_7C15,
        };
        rng.next_u64();
        rng
    }

    /// A child stream, independent of the parent's future draws.
    pub fn fork(&mut self) -> Self {
        Self::new(self.next_u64())
    }

    /// A stream keyed by (seed, stream): the simulator's, one per scene and purpose.
    pub fn keyed(seed: u64, stream: u64) -> Self {
        Self {
            state: key_hash(&[seed, stream]),
        }
    }

    pub fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        mix64(self.state)
    }

    /// Uniform in [0, 1) with 24 bits of mantissa.
    pub fn uniform(&mut self) -> f32 {
        unit_f32(self.next_u64())
    }

    /// Uniform in [lo, hi).
    pub fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.uniform()
    }

    /// True with probability `p`.
    pub fn chance(&mut self, p: f32) -> bool {
        self.uniform() < p
    }

    /// Uniform in the open interval (0, 1): safe for `ln`.
    pub fn uniform_open(&mut self) -> f32 {
        ((self.next_u64() >> 40) as f32 + 0.5) * (1.0 / (1u64 << 24) as f32)
    }

    /// Uniform integer in [0, n) by multiply-shift (the model's draws).
    pub fn below(&mut self, n: usize) -> usize {
        (((self.next_u64() >> 32) * n as u64) >> 32) as usize
    }

    /// Integer in [0, n) by the remainder, 0 when n is 0. The simulator's scenes are defined
    /// by these draws, so it keeps them rather than [`Rng::below`]'s: a seed's scene stays
    /// the same scene.
    pub fn index(&mut self, n: usize) -> usize {
        if n == 0 {
            0
        } else {
            (self.next_u64() % n as u64) as usize
        }
    }

    /// Standard normal (Box-Muller).
    pub fn normal(&mut self) -> f32 {
        let u1 = self.uniform_open();
        let u2 = self.uniform();
        (-2.0 * u1.ln()).sqrt() * (std::f32::consts::TAU * u2).cos()
    }

    pub fn normal_vec(&mut self, n: usize) -> Vec<f32> {
        (0..n).map(|_| self.normal()).collect()
    }

    pub fn uniform_vec(&mut self, n: usize) -> Vec<f32> {
        (0..n).map(|_| self.uniform()).collect()
    }

    /// A tensor of standard normals.
    pub fn normal_tensor<const D: usize>(
        &mut self,
        shape: [usize; D],
        device: &Device,
    ) -> Tensor<D> {
        let n = shape.iter().product();
        super::tensor::tensor_from(self.normal_vec(n), shape, device)
    }

    /// A tensor of uniforms in the open interval (0, 1).
    pub fn uniform_open_tensor<const D: usize>(
        &mut self,
        shape: [usize; D],
        device: &Device,
    ) -> Tensor<D> {
        let n = shape.iter().product();
        let v: Vec<f32> = (0..n).map(|_| self.uniform_open()).collect();
        super::tensor::tensor_from(v, shape, device)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn normal_has_unit_moments() {
        let mut rng = Rng::new(7);
        let v = rng.normal_vec(200_000);
        let mean = v.iter().sum::<f32>() / v.len() as f32;
        let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f32>() / v.len() as f32;
        assert!(mean.abs() < 0.01, "mean {mean}");
        assert!((var - 1.0).abs() < 0.02, "var {var}");
    }

    #[test]
    fn same_seed_same_stream() {
        let a: Vec<u64> = (0..4)
            .scan(Rng::new(3), |r, _| Some(r.next_u64()))
            .collect();
        let b: Vec<u64> = (0..4)
            .scan(Rng::new(3), |r, _| Some(r.next_u64()))
            .collect();
        let c: Vec<u64> = (0..4)
            .scan(Rng::new(4), |r, _| Some(r.next_u64()))
            .collect();
        assert_eq!(a, b);
        assert_ne!(a, c);
    }

    #[test]
    fn draws_depend_only_on_keys() {
        assert_eq!(uniform(&[1, 2, 3]), uniform(&[1, 2, 3]));
        assert_ne!(uniform(&[1, 2, 3]), uniform(&[1, 2, 4]));
        assert_ne!(uniform(&[1, 2, 3]), uniform(&[3, 2, 1]));
        let mut a = Rng::keyed(7, 1);
        let mut b = Rng::keyed(7, 1);
        assert_eq!(a.next_u64(), b.next_u64());
        assert_ne!(Rng::keyed(7, 2).next_u64(), Rng::keyed(7, 1).next_u64());
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
