//! Judging a segmentation model on labelled scans: a confusion matrix over labelled returns
//! (dropped rays and unlabelled points are not scored), per-class precision, recall and IoU,
//! the mean IoU over the named classes present in the ground truth and over car and person
//! (the paper's Table 4), and a comparison picture (input, ground truth, each model's
//! prediction) like the paper's Figure 7.

use std::path::Path;

use anyhow::{Result, bail};
use burn::tensor::Device;
use plotters::prelude::*;
use serde::Serialize;

use super::SegModel;
use super::classes::{CAR_PERSON, CLASSES, NUM_CLASSES, SCORED, color, is_class};
use super::data::{CHANNELS, SegDataset};
use super::net::SegNet;
use crate::lidar::range_image::column_azimuth;
use crate::report::plot::{register_font, viridis};
use crate::util::fs::write_atomic;
use crate::util::png::encode_rgb;
use crate::util::tensor::{tensor_from, tensor_to_vec};

/// Counts of (true class, predicted class) over labelled returns.
#[derive(Debug, Clone, Default)]
pub struct Confusion {
    counts: [[u64; NUM_CLASSES]; NUM_CLASSES],
}

/// One class's scores; `None` where undefined (no such points and no such predictions).
#[derive(Debug, Clone, Serialize)]
pub struct ClassScore {
    pub class: String,
    /// Labelled returns of this class.
    pub points: u64,
    /// Returns predicted as this class, and those of them labelled so: with `points` the
    /// counts that pool scores over recordings exactly.
    pub predicted: u64,
    pub correct: u64,
    pub precision: Option<f64>,
    pub recall: Option<f64>,
    pub iou: Option<f64>,
}

impl Confusion {
    pub fn add(&mut self, truth: u8, predicted: u8) {
        if let (Some(row), true) = (
            self.counts.get_mut(truth as usize),
            (predicted as usize) < NUM_CLASSES,
        ) {
            row[predicted as usize] += 1;
        }
    }

    pub fn merge(&mut self, other: &Confusion) {
        for (a, b) in self
            .counts
            .iter_mut()
            .flatten()
            .zip(other.counts.iter().flatten())
        {
            *a += b;
        }
    }

    pub fn scores(&self) -> Vec<ClassScore> {
        let ratio = |a: u64, b: u64| (b > 0).then(|| a as f64 / b as f64);
        (0..NUM_CLASSES)
            .map(|c| {
                let tp = self.counts[c][c];
                let truth: u64 = self.counts[c].iter().sum();
                let predicted: u64 = self.counts.iter().map(|row| row[c]).sum();
                ClassScore {
                    class: CLASSES[c].to_string(),
                    points: truth,
                    predicted,
                    correct: tp,
                    precision: ratio(tp, predicted),
                    recall: ratio(tp, truth),
                    iou: ratio(tp, truth + predicted - tp),
                }
            })
            .collect()
    }
}

/// Mean IoU over `classes` that have ground-truth points.
pub fn mean_iou(scores: &[ClassScore], classes: impl IntoIterator<Item = usize>) -> Option<f64> {
    let ious: Vec<f64> = classes
        .into_iter()
        .filter(|&c| scores[c].points > 0)
        .filter_map(|c| scores[c].iou)
        .collect();
    (!ious.is_empty()).then(|| ious.iter().sum::<f64>() / ious.len() as f64)
}

/// The scores of one model on one dataset.
#[derive(Debug, Clone, Serialize)]
pub struct EvalReport {
    pub model: String,
    pub files: Vec<String>,
    pub scans: usize,
    /// Whole revolutions.
    #[serde(flatten)]
    pub scores: Scores,
    /// The frontal 90 degrees only (azimuth within 45 degrees of straight ahead): the view
    /// of the paper's KITTI-frontal evaluation.
    pub frontal: Scores,
}

/// Scores over one set of labelled returns.
#[derive(Debug, Clone, Serialize)]
pub struct Scores {
    /// Labelled returns scored.
    pub points: u64,
    pub classes: Vec<ClassScore>,
    /// Mean IoU over car, person, road, sidewalk, building, vegetation and pole (those present).
    pub miou: Option<f64>,
    /// Mean IoU over car and person (the paper's Table 4).
    pub miou_car_person: Option<f64>,
    /// The confusion matrix: `confusion[t][p]` returns labelled `t` predicted as `p`, in the
    /// order of `classes` (what is taken for what).
    pub confusion: Vec<Vec<u64>>,
}

impl Scores {
    pub fn new(confusion: &Confusion) -> Self {
        let classes = confusion.scores();
        Scores {
            points: classes.iter().map(|c| c.points).sum(),
            miou: mean_iou(&classes, SCORED),
            miou_car_person: mean_iou(&classes, CAR_PERSON),
            classes,
            confusion: confusion.counts.iter().map(|row| row.to_vec()).collect(),
        }
    }
}

/// Whether column `j` of `width` looks within 45 degrees of straight ahead.
pub fn is_frontal(j: usize, width: usize) -> bool {
    column_azimuth(j, width).abs() <= std::f32::consts::FRAC_PI_4
}

/// The predicted class of every pixel of every scan (whole revolutions, circular padding).
pub fn predict(net: &SegNet, data: &SegDataset, device: &Device) -> Vec<Vec<u8>> {
    const BATCH: usize = 4;
    let (h, w) = (data.height, data.width);
    let n = h * w;
    let mut out = Vec::with_capacity(data.len());
    for chunk in data.scans.chunks(BATCH) {
        let input: Vec<f32> = chunk.iter().flat_map(|s| s.input.iter().copied()).collect();
        let x = tensor_from(input, [chunk.len(), CHANNELS, h, w], device);
        let logits = tensor_to_vec(net.forward(x, true));
        for s in 0..chunk.len() {
            let scan = &logits[s * NUM_CLASSES * n..(s + 1) * NUM_CLASSES * n];
            out.push(
                (0..n)
                    .map(|k| {
                        (0..NUM_CLASSES)
                            .max_by(|&a, &b| scan[a * n + k].total_cmp(&scan[b * n + k]))
                            .unwrap_or(0) as u8
                    })
                    .collect(),
            );
        }
    }
    out
}

/// The confusion matrix of `predictions` over the labelled returns of `data` in the columns
/// `keep` accepts.
fn tally(data: &SegDataset, predictions: &[Vec<u8>], keep: impl Fn(usize) -> bool) -> Confusion {
    let mut confusion = Confusion::default();
    for (scan, pred) in data.scans.iter().zip(predictions) {
        for (k, (&t, &p)) in scan.target.iter().zip(pred).enumerate() {
            if is_class(t) && keep(k % data.width) {
                confusion.add(t, p);
            }
        }
    }
    confusion
}

/// The confusion matrix of `net` over every labelled return of `data`.
pub fn confusion(net: &SegNet, data: &SegDataset, device: &Device) -> Confusion {
    tally(data, &predict(net, data, device), |_| true)
}

/// Scores `model` on every labelled return of `data`, and on the frontal view alone.
pub fn evaluate(
    model: &SegModel,
    name: &str,
    data: &SegDataset,
    device: &Device,
) -> Result<EvalReport> {
    check_grid(model, data)?;
    let predictions = predict(&model.net, data, device);
    let w = data.width;
    Ok(EvalReport {
        model: name.to_string(),
        files: data.files.iter().map(|f| f.display().to_string()).collect(),
        scans: data.len(),
        scores: Scores::new(&tally(data, &predictions, |_| true)),
        frontal: Scores::new(&tally(data, &predictions, |j| is_frontal(j, w))),
    })
}

fn check_grid(model: &SegModel, data: &SegDataset) -> Result<()> {
    let p = &model.info.profile;
    if (p.beams(), p.columns) != (data.height, data.width) {
        bail!(
            "the model was trained on a {}x{} grid, the data is projected on {}x{}",
            p.beams(),
            p.columns,
            data.height,
            data.width
        );
    }
    Ok(())
}

/// Pixel size of each picture row (range images are drawn at 2x).
const SCALE: usize = 2;
const CAPTION: usize = 22;

/// Writes a PNG: scan `index` of `data` as range, ground truth and the prediction of each
/// model (rows, captioned), with a class legend at the bottom. Black: no return (and, in
/// the ground truth, no label).
pub fn picture(
    models: &[(String, SegModel)],
    data: &SegDataset,
    index: usize,
    path: &Path,
) -> Result<()> {
    let Some(scan) = data.scans.get(index) else {
        bail!("scan {index} does not exist ({} scans)", data.len());
    };
    let device = Device::flex();
    let (h, w) = (data.height, data.width);
    let n = h * w;
    let one = SegDataset {
        height: h,
        width: w,
        scans: vec![scan.clone()],
        files: vec![],
    };
    let mut rows: Vec<(String, Vec<[u8; 3]>)> = Vec::new();
    let range: Vec<[u8; 3]> = (0..n)
        .map(|k| {
            if scan.is_return(k) {
                // Range channel is metres / 20: colour by log range over 1.5-80 m.
                let r = scan.input[3 * n + k] * 20.0;
                viridis((r.max(1.5) / 1.5).ln() / (80.0f32 / 1.5).ln())
            } else {
                [0, 0, 0]
            }
        })
        .collect();
    rows.push((
        "input: range (x, y, z, range and return mask go in)".into(),
        range,
    ));
    rows.push((
        "ground truth".into(),
        scan.target.iter().map(|&t| color(t)).collect(),
    ));
    for (name, model) in models {
        check_grid(model, &one)?;
        let pred = predict(&model.net, &one, &device).remove(0);
        let colours = (0..n)
            .map(|k| {
                if scan.is_return(k) {
                    color(pred[k])
                } else {
                    [0, 0, 0]
                }
            })
            .collect();
        rows.push((name.clone(), colours));
    }
    let (pw, row_h) = (w * SCALE, CAPTION + h * SCALE);
    let ph = rows.len() * row_h + CAPTION + 4;
    let mut buf = vec![255u8; pw * ph * 3];
    for (r, (_, colours)) in rows.iter().enumerate() {
        let top = r * row_h + CAPTION;
        for y in 0..h * SCALE {
            for x in 0..pw {
                let c = colours[(y / SCALE) * w + x / SCALE];
                let o = ((top + y) * pw + x) * 3;
                buf[o..o + 3].copy_from_slice(&c);
            }
        }
    }
    register_font();
    {
        let area = BitMapBackend::with_buffer(&mut buf, (pw as u32, ph as u32)).into_drawing_area();
        let style = ("sans-serif", 15).into_font().color(&BLACK);
        for (r, (caption, _)) in rows.iter().enumerate() {
            area.draw(&Text::new(
                caption.as_str(),
                (6, (r * row_h + 3) as i32),
                style.clone(),
            ))?;
        }
        let legend_y = (rows.len() * row_h + 4) as i32;
        let mut x = 6i32;
        for (c, name) in CLASSES.iter().enumerate() {
            let [r, g, b] = color(c as u8);
            area.draw(&Rectangle::new(
                [(x, legend_y + 2), (x + 12, legend_y + 14)],
                RGBColor(r, g, b).filled(),
            ))?;
            area.draw(&Text::new(*name, (x + 16, legend_y), style.clone()))?;
            x += 24 + 9 * name.len() as i32;
        }
        area.present()?;
    }
    write_atomic(path, &encode_rgb(pw as u32, ph as u32, &buf)?)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scores_follow_the_definitions() {
        let mut m = Confusion::default();
        // car: 3 right, 1 called road; road: 5 right, 1 called car; person never seen.
        for _ in 0..3 {
            m.add(0, 0);
        }
        m.add(0, 2);
        for _ in 0..5 {
            m.add(2, 2);
        }
        m.add(2, 0);
        let s = m.scores();
        assert_eq!(s[0].points, 4);
        assert_eq!((s[0].predicted, s[0].correct), (4, 3));
        assert_eq!((s[2].points, s[2].predicted, s[2].correct), (6, 6, 5));
        assert_eq!(Scores::new(&m).confusion[0][2], 1);
        assert_eq!(s[0].precision, Some(0.75));
        assert_eq!(s[0].recall, Some(0.75));
        assert_eq!(s[0].iou, Some(3.0 / 5.0));
        assert_eq!(s[2].iou, Some(5.0 / 7.0));
        assert_eq!(s[1].iou, None);
        // Person has no points: it is left out of both means.
        assert_eq!(mean_iou(&s, CAR_PERSON), Some(0.6));
        assert_eq!(mean_iou(&s, SCORED), Some((0.6 + 5.0 / 7.0) / 2.0));
    }
}
