//! Adam (Kingma and Ba) over weights held on the host, with torch's defaults (beta 0.9, 0.999;
//! eps 1e-8): the same update as burn's `Adam`. The caller hands over its weights and their
//! gradients in the same order at every step.

use std::ops::Range;

/// The moments of every weight and the step count.
#[derive(Debug, Clone)]
pub struct Adam {
    m: Vec<f32>,
    v: Vec<f32>,
    t: i32,
}

impl Adam {
    /// For `n` weights.
    pub fn new(n: usize) -> Self {
        Adam {
            m: vec![0.0; n],
            v: vec![0.0; n],
            t: 0,
        }
    }

    /// One step at learning rate `lr`.
    pub fn step<'a>(
        &mut self,
        params: impl IntoIterator<Item = &'a mut f32>,
        grads: impl IntoIterator<Item = &'a f32>,
        lr: f32,
    ) {
        let k = self.next_step();
        let moments = self.m.iter_mut().zip(self.v.iter_mut());
        for ((x, g), (m, v)) in params.into_iter().zip(grads).zip(moments) {
            k.update(x, *g, m, v, lr);
        }
    }

    /// One step at learning rate `lr` over the weights `params[r]` of each run `r` (ascending,
    /// not overlapping), with their gradients at the same indices of `grads`: the same update as
    /// [`Adam::step`] over those weights in order, on slices the compiler can vectorise.
    pub fn step_runs(&mut self, params: &mut [f32], grads: &[f32], runs: &[Range<usize>], lr: f32) {
        let k = self.next_step();
        let mut at = 0;
        for r in runs {
            let n = r.len();
            let (m, v) = (&mut self.m[at..at + n], &mut self.v[at..at + n]);
            let xs = params[r.clone()].iter_mut().zip(&grads[r.clone()]);
            for ((x, g), (m, v)) in xs.zip(m.iter_mut().zip(v.iter_mut())) {
                k.update(x, *g, m, v, lr);
            }
            at += n;
        }
    }

    fn next_step(&mut self) -> Step {
        self.t += 1;
        Step {
            c1: 1.0 - B1.powi(self.t),
            c2: 1.0 - B2.powi(self.t),
        }
    }
}

const B1: f32 = 0.9;
const B2: f32 = 0.999;
const EPS: f32 = 1e-8;

/// The bias corrections of one step.
#[derive(Clone, Copy)]
struct Step {
    c1: f32,
    c2: f32,
}

impl Step {
    #[inline(always)]
    fn update(self, x: &mut f32, g: f32, m: &mut f32, v: &mut f32, lr: f32) {
        *m = B1 * *m + (1.0 - B1) * g;
        *v = B2 * *v + (1.0 - B2) * g * g;
        *x -= lr * (*m / self.c1) / ((*v / self.c2).sqrt() + EPS);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_first_step_moves_each_weight_by_the_rate_against_its_gradient() {
        let mut x = [1.0f32, -2.0, 0.5];
        let mut adam = Adam::new(3);
        adam.step(&mut x, &[0.3, -4.0, 0.0], 0.1);
        // Bias-corrected, the first step is lr * sign(g) (0 where g is 0).
        assert!(
            (x[0] - 0.9).abs() < 1e-5 && (x[1] + 1.9).abs() < 1e-5,
            "{x:?}"
        );
        assert_eq!(x[2], 0.5);
    }

    #[test]
    fn a_step_over_runs_is_the_step_over_their_weights() {
        let runs = [1..3, 4..7];
        let (mut a, mut b) = ([0.5f32, -1.0, 2.0, 0.1, 3.0, -0.2, 0.7, 9.0], [0.0f32; 8]);
        b.copy_from_slice(&a);
        let (mut by_runs, mut by_items) = (Adam::new(5), Adam::new(5));
        for k in 0..4 {
            let g: Vec<f32> = (0..8).map(|i| ((i * 7 + k * 3) % 5) as f32 - 2.0).collect();
            by_runs.step_runs(&mut a, &g, &runs, 0.05);
            let picked = |i: &usize| runs.iter().any(|r| r.contains(i));
            let params = b
                .iter_mut()
                .enumerate()
                .filter(|(i, _)| picked(i))
                .map(|(_, x)| x);
            let grads = g
                .iter()
                .enumerate()
                .filter(|(i, _)| picked(i))
                .map(|(_, g)| g);
            by_items.step(params, grads, 0.05);
        }
        assert_eq!(a, b);
        assert_eq!((a[0], a[3], a[7]), (0.5, 0.1, 9.0));
    }

    #[test]
    fn it_minimises_a_quadratic() {
        let mut x = [3.0f32, -5.0];
        let mut adam = Adam::new(2);
        for _ in 0..500 {
            let g = [2.0 * x[0], 2.0 * (x[1] + 1.0)];
            adam.step(&mut x, &g, 0.05);
        }
        assert!(x[0].abs() < 0.05 && (x[1] + 1.0).abs() < 0.05, "{x:?}");
    }
}
