//! Ray-drop calibration curves: reliability of x_n per bin, as JSON and as a chart.

use std::path::Path;

use anyhow::{Context, Result};
use serde_json::json;

/// A reliability curve: per x_n bin, the summed x_n, the drops and the pixel count.
pub(crate) struct Reliability(Vec<(f64, f64, usize)>);

impl Reliability {
    pub(crate) fn new(bins: usize) -> Self {
        Reliability(vec![(0.0, 0.0, 0); bins])
    }

    pub(crate) fn add(&mut self, x_n: f64, dropped: bool) {
        let n = self.0.len();
        let bin = &mut self.0[((x_n * n as f64) as usize).min(n - 1)];
        bin.0 += x_n;
        bin.1 += f64::from(u8::from(dropped));
        bin.2 += 1;
    }

    /// Observed drop rate per bin; NaN where a bin has too few pixels to say.
    pub(crate) fn observed(&self) -> Vec<f64> {
        self.0
            .iter()
            .map(|(_, d, c)| if *c >= 100 { d / *c as f64 } else { f64::NAN })
            .collect()
    }

    pub(crate) fn json(&self) -> serde_json::Value {
        let n = self.0.len() as f64;
        self.0
            .iter()
            .enumerate()
            .map(|(i, (sp, sd, c))| {
                json!({
                    "bin": format!("{:.1}-{:.1}", i as f64 / n, (i + 1) as f64 / n),
                    "pixels": c, "mean_xn": sp / (*c).max(1) as f64,
                    "observed_drop_rate": sd / (*c).max(1) as f64,
                })
            })
            .collect()
    }
}

/// The reliability curves of the calibrated and the raw x_n against the diagonal.
pub(crate) fn reliability_chart(
    path: &Path,
    calibrated: &Reliability,
    raw: &Reliability,
) -> Result<()> {
    use rangegan_mcap::report::plot::{FITTED, LineChart, SIM, Series, line_chart};
    use rangegan_mcap::util::fs::write_atomic;
    let n = calibrated.0.len();
    let x: Vec<f64> = (0..n).map(|i| (i as f64 + 0.5) / n as f64).collect();
    let (cal, unc) = (calibrated.observed(), raw.observed());
    let chart = LineChart {
        title: "Ray-drop calibration, 26 held-out KITTI scans",
        x_label: "predicted drop probability x_n (bin centre)",
        y_label: "observed drop rate",
        x: &x,
        series: &[
            Series {
                label: "calibrated x_n (shipped)",
                colour: FITTED,
                y: &cal,
            },
            Series {
                label: "raw x_n of the generator",
                colour: SIM,
                y: &unc,
            },
            Series {
                label: "perfect calibration",
                colour: plotters::style::RGBColor(120, 120, 120),
                y: &x,
            },
        ],
    };
    write_atomic(path, &line_chart(&chart)?)
        .with_context(|| format!("failed to write {}", path.display()))
}
