//! Scoring: absolute range errors per method and scan (near and far), and their summary
//! per case.

use serde_json::json;

/// Truth at or below this is "near".
pub(crate) const NEAR_M: f32 = 30.0;

/// Error sums of one method on one scan.
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct ErrorSums {
    near: f64,
    near_n: usize,
    far: f64,
    far_n: usize,
    /// Pixels more than 1 m off the true surface.
    off_1m: usize,
    /// Pixels the method left empty, scored with the fallback.
    holes: usize,
}

impl ErrorSums {
    pub(crate) fn add(&mut self, o: &ErrorSums) {
        self.near += o.near;
        self.near_n += o.near_n;
        self.far += o.far;
        self.far_n += o.far_n;
        self.off_1m += o.off_1m;
        self.holes += o.holes;
    }

    pub(crate) fn n(&self) -> usize {
        self.near_n + self.far_n
    }

    pub(crate) fn mae(&self) -> f64 {
        (self.near + self.far) / self.n().max(1) as f64
    }
}

/// Absolute errors in meters over every pixel where `truth` is measured and `mask` allows,
/// split near (truth <= 30 m) / far. Each prediction comes with its fallback: where the
/// method leaves a pixel empty it is scored with what its user gets there (`convert`'s
/// fills: x_d; an interpolation baseline: the nearest return), never skipped; a pixel
/// nothing answers counts as a prediction of 0 m.
pub(crate) fn errors(
    truth: &[f32],
    preds: &[(&[f32], &[f32])],
    mask: &dyn Fn(usize) -> bool,
) -> Vec<ErrorSums> {
    let mut sums = vec![ErrorSums::default(); preds.len()];
    for k in 0..truth.len() {
        if truth[k] <= 0.0 || !mask(k) {
            continue;
        }
        let near = truth[k] <= NEAR_M;
        for (s, (p, fallback)) in sums.iter_mut().zip(preds) {
            let hole = p[k] <= 0.0;
            let value = if hole { fallback[k].max(0.0) } else { p[k] };
            let e = f64::from((value - truth[k]).abs());
            if near {
                s.near += e;
                s.near_n += 1;
            } else {
                s.far += e;
                s.far_n += 1;
            }
            s.off_1m += usize::from(e > 1.0);
            s.holes += usize::from(hole);
        }
    }
    sums
}

/// Per method over all scans: MAE, MAE near (<= 30 m) and far, and the share of pixels more
/// than 1 m off.
pub(crate) fn summarize(per: &[Vec<ErrorSums>], names: &[String]) -> serde_json::Value {
    let mut m = serde_json::Map::new();
    let mut total = ErrorSums::default();
    for (i, name) in names.iter().enumerate() {
        let mut t = ErrorSums::default();
        for p in per {
            t.add(&p[i]);
        }
        m.insert(
            name.clone(),
            json!({
                "mae": t.mae(),
                "mae_near": t.near / t.near_n.max(1) as f64,
                "mae_far": t.far / t.far_n.max(1) as f64,
                "off_1m": t.off_1m as f64 / t.n().max(1) as f64,
                "holes": t.holes as f64 / t.n().max(1) as f64,
            }),
        );
        total = t;
    }
    m.insert("pixels".into(), json!(total.n()));
    m.insert("near_pixels".into(), json!(total.near_n));
    m.insert("far_pixels".into(), json!(total.far_n));
    m.insert("scans".into(), json!(per.len()));
    serde_json::Value::Object(m)
}
