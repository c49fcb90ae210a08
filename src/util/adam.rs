//! Adam (Kingma and Ba) over weights held on the host, with torch's defaults (beta 0.9, 0.999;
//! eps 1e-8): the same update as burn's `Adam`. The caller hands over its weights and their
//! gradients in the same order at every step.

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
        let (b1, b2, eps) = (0.9f32, 0.999f32, 1e-8f32);
        self.t += 1;
        let c1 = 1.0 - b1.powi(self.t);
        let c2 = 1.0 - b2.powi(self.t);
        let moments = self.m.iter_mut().zip(self.v.iter_mut());
        for ((x, g), (m, v)) in params.into_iter().zip(grads).zip(moments) {
            *m = b1 * *m + (1.0 - b1) * g;
            *v = b2 * *v + (1.0 - b2) * g * g;
            *x -= lr * (*m / c1) / ((*v / c2).sqrt() + eps);
        }
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
