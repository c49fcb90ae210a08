//! The segmentation network's training losses: cross-entropy weighted per class, and the
//! Lovász-softmax surrogate of per-class IoU (Berman et al., CVPR 2018, as RangeNet++ and
//! SqueezeSegV3 train with), where every class present in a batch counts equally however
//! few pixels it holds, which is what person and pole need.
//!
//! The Lovász extension is linear in the per-pixel errors once their order is fixed, so the
//! order and its weights are computed on the host and the loss is a weighted sum of tensor
//! errors: the same value and gradient as sorting inside the graph.
//!
//! A pixel with the partial label [`NOT_CAR_OR_PERSON`] counts in the cross-entropy as the
//! event "any class but car and person" (-ln(1 - p_car - p_person)), and in the Lovász term
//! as a known negative of car and person.

use burn::tensor::Tensor;
use burn::tensor::activation::log_softmax;

use super::classes::{CAR_PERSON, NOT_CAR_OR_PERSON, NUM_CLASSES, is_class};

/// Per-pixel targets `[b, H, W]` as class weight at the true class and 0 elsewhere
/// (`[b, classes, H, W]`), and the sum of the weights (the loss's normaliser).
pub fn weighted_one_hot(
    target: &[u8],
    n: usize,
    class_weight: &[f32; NUM_CLASSES],
) -> (Vec<f32>, f32) {
    let mut out = vec![0.0f32; target.len() * NUM_CLASSES];
    let mut norm = 0.0f32;
    for (idx, &t) in target.iter().enumerate() {
        if !is_class(t) {
            continue;
        }
        let (s, k) = (idx / n, idx % n);
        let wt = class_weight[t as usize];
        out[(s * NUM_CLASSES + t as usize) * n + k] = wt;
        norm += wt;
    }
    (out, norm.max(1e-6))
}

/// Cross-entropy weighted per pixel: -sum(weights * log_softmax(logits)) / norm.
pub fn weighted_cross_entropy(logits: Tensor<4>, weights: Tensor<4>, norm: f32) -> Tensor<1> {
    log_softmax(logits, 1).mul(weights).sum().div_scalar(-norm)
}

/// The [`NOT_CAR_OR_PERSON`] pixels of `target` (`[b, n]`) as a `[b, 1, n]` mask, and their
/// count.
pub fn partial_mask(target: &[u8]) -> (Vec<f32>, f32) {
    let mask: Vec<f32> = target
        .iter()
        .map(|&t| f32::from(t == NOT_CAR_OR_PERSON))
        .collect();
    let count = mask.iter().sum();
    (mask, count)
}

/// The summed cross-entropy of the partial label: -sum(mask * ln(1 - p_car - p_person)),
/// the log-probability of the other classes taken as one log-sum-exp.
///
/// # Shapes
/// - logits: `[b, classes, H, W]`, mask: `[b, 1, H, W]`
pub fn partial_cross_entropy(logits: Tensor<4>, mask: Tensor<4>) -> Tensor<1> {
    let first = CAR_PERSON.len();
    let rest = log_softmax(logits, 1).narrow(1, first, NUM_CLASSES - first); // [b, c-2, H, W]
    let top = rest.clone().max_dim(1).detach(); // [b, 1, H, W]
    let lse = (rest - top.clone()).exp().sum_dim(1).log() + top; // [b, 1, H, W]
    lse.mul(mask).sum().neg()
}

/// What the Lovász-softmax term needs beside the network's class probabilities: the
/// one-hot targets and each pixel's weight in the sorted-error sum, both
/// `[b, classes, H, W]` as host vectors (0 at ignored pixels).
#[derive(Debug, Clone)]
pub struct LovaszTerms {
    pub one_hot: Vec<f32>,
    pub weights: Vec<f32>,
}

/// The Lovász weights for probabilities `probs` (`[b, classes, n]`, host) against
/// `target` (`[b, n]`): per class present in the batch, the pixels' errors |1[class] - p|
/// sorted in decreasing order, each weighted by the step of the Jaccard loss it causes,
/// averaged over the present classes.
pub fn lovasz_terms(probs: &[f32], target: &[u8], n: usize) -> LovaszTerms {
    let mut one_hot = vec![0.0f32; probs.len()];
    for (idx, &t) in target.iter().enumerate() {
        if is_class(t) {
            one_hot[((idx / n) * NUM_CLASSES + t as usize) * n + idx % n] = 1.0;
        }
    }
    let at = |c: usize, idx: usize| ((idx / n) * NUM_CLASSES + c) * n + idx % n;
    let labelled: Vec<usize> = (0..target.len()).filter(|&i| is_class(target[i])).collect();
    let partial: Vec<usize> = (0..target.len())
        .filter(|&i| target[i] == NOT_CAR_OR_PERSON)
        .collect();
    let mut weights = vec![0.0f32; probs.len()];
    let mut per_class: Vec<(usize, Vec<(usize, f32)>)> = Vec::new();
    for c in 0..NUM_CLASSES {
        let positives = labelled.iter().filter(|&&i| target[i] == c as u8).count();
        if positives == 0 {
            continue;
        }
        let known_negatives: &[usize] = if CAR_PERSON.contains(&c) {
            &partial
        } else {
            &[]
        };
        let mut order: Vec<(usize, f32)> = labelled
            .iter()
            .chain(known_negatives)
            .map(|&i| (i, (one_hot[at(c, i)] - probs[at(c, i)]).abs()))
            .collect();
        order.sort_by(|a, b| b.1.total_cmp(&a.1));
        let (mut fg_seen, mut bg_seen, mut previous) = (0.0f64, 0.0f64, 0.0f64);
        let total = positives as f64;
        let steps = order
            .iter()
            .map(|&(i, _)| {
                if target[i] == c as u8 {
                    fg_seen += 1.0;
                } else {
                    bg_seen += 1.0;
                }
                let jaccard = 1.0 - (total - fg_seen) / (total + bg_seen);
                let step = jaccard - previous;
                previous = jaccard;
                (i, step as f32)
            })
            .collect();
        per_class.push((c, steps));
    }
    let present = per_class.len().max(1) as f32;
    for (c, steps) in per_class {
        for (i, step) in steps {
            weights[at(c, i)] = step / present;
        }
    }
    LovaszTerms { one_hot, weights }
}

/// The Lovász-softmax loss from the network's class probabilities and [`lovasz_terms`].
pub fn lovasz_softmax(probs: Tensor<4>, one_hot: Tensor<4>, weights: Tensor<4>) -> Tensor<1> {
    (one_hot - probs).abs().mul(weights).sum()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::segment::classes::IGNORE;
    use crate::util::tensor::tensor_from;
    use burn::tensor::Device;

    #[test]
    fn cross_entropy_matches_the_formula_and_skips_ignored_pixels() {
        let device = Device::flex();
        // One image, 1x2 pixels: pixel 0 is class 2, pixel 1 is ignored.
        let mut w = [1.0f32; NUM_CLASSES];
        w[2] = 3.0;
        let (weights, norm) = weighted_one_hot(&[2, IGNORE], 2, &w);
        assert_eq!(norm, 3.0);
        let logits: Vec<f32> = (0..NUM_CLASSES * 2)
            .map(|i| (i as f32 * 0.37).sin())
            .collect();
        let expected = {
            let l: Vec<f32> = (0..NUM_CLASSES).map(|c| logits[c * 2]).collect();
            let lse = l.iter().map(|v| v.exp()).sum::<f32>().ln();
            lse - l[2]
        };
        let loss = weighted_cross_entropy(
            tensor_from(logits, [1, NUM_CLASSES, 1, 2], &device),
            tensor_from(weights, [1, NUM_CLASSES, 1, 2], &device),
            norm,
        )
        .into_scalar::<f32>();
        assert!((loss - expected).abs() < 1e-5, "{loss} vs {expected}");
    }

    /// Probabilities that put all mass on `pred` per pixel.
    fn hard(pred: &[u8]) -> Vec<f32> {
        let n = pred.len();
        let mut p = vec![0.0f32; NUM_CLASSES * n];
        for (k, &c) in pred.iter().enumerate() {
            p[c as usize * n + k] = 1.0;
        }
        p
    }

    fn loss(probs: Vec<f32>, target: &[u8]) -> f32 {
        let n = target.len();
        let terms = lovasz_terms(&probs, target, n);
        let device = Device::flex();
        let t = |v: Vec<f32>| tensor_from(v, [1, NUM_CLASSES, 1, n], &device);
        lovasz_softmax(t(probs), t(terms.one_hot), t(terms.weights)).into_scalar::<f32>()
    }

    #[test]
    fn on_hard_predictions_lovasz_is_one_minus_the_mean_iou_of_present_classes() {
        // Truth: 4 road (2), 2 person (1), 1 ignored; prediction: one road read as person,
        // one person read as car (0).
        let target = [2, 2, 2, 2, 1, 1, IGNORE];
        let pred = [2, 2, 2, 1, 1, 0, 5];
        // road IoU 3/4; person IoU 1/(2+2-1) = 1/3; car is absent from the truth.
        let expected = 1.0 - (0.75 + 1.0 / 3.0) / 2.0;
        let got = loss(hard(&pred), &target);
        assert!((got - expected as f32).abs() < 1e-5, "{got} vs {expected}");
        assert!(loss(hard(&[2, 2, 2, 2, 1, 1, 3]), &target).abs() < 1e-6);
    }

    #[test]
    fn lovasz_counts_a_small_class_as_much_as_a_large_one() {
        // 98 road pixels and 2 person pixels; missing both persons costs as much as
        // missing 98 road pixels' worth of IoU, where cross-entropy would see 2 %.
        let mut target = vec![2u8; 100];
        target[0] = 1;
        target[1] = 1;
        let all_road = vec![2u8; 100];
        let got = loss(hard(&all_road), &target);
        // person IoU 0, road IoU 98/100.
        let expected = 1.0 - (0.0 + 0.98) / 2.0;
        assert!((got - expected).abs() < 1e-5, "{got}");
    }

    #[test]
    fn the_partial_label_costs_the_probability_of_car_or_person() {
        let device = Device::flex();
        // Pixel 0: neither car nor person; pixel 1: road, which the partial term ignores.
        let (mask, count) = partial_mask(&[NOT_CAR_OR_PERSON, 2]);
        assert_eq!(count, 1.0);
        let logits: Vec<f32> = (0..NUM_CLASSES * 2)
            .map(|i| (i as f32 * 0.61).cos())
            .collect();
        let p: Vec<f32> = {
            let e: Vec<f32> = (0..NUM_CLASSES).map(|c| logits[c * 2].exp()).collect();
            let z: f32 = e.iter().sum();
            e.iter().map(|v| v / z).collect()
        };
        let expected = -(1.0 - p[0] - p[1]).ln();
        let got = partial_cross_entropy(
            tensor_from(logits, [1, NUM_CLASSES, 1, 2], &device),
            tensor_from(mask, [1, 1, 1, 2], &device),
        )
        .into_scalar::<f32>();
        assert!((got - expected).abs() < 1e-5, "{got} vs {expected}");
    }

    #[test]
    fn lovasz_counts_a_partial_pixel_read_as_car_against_car_only() {
        // Two cars, one road pixel, one pixel known to be neither car nor person.
        let target = [0, 0, 2, NOT_CAR_OR_PERSON];
        // Read as car: car IoU 2/3, road 1.
        let as_car = loss(hard(&[0, 0, 2, 0]), &target);
        assert!(
            (as_car - (1.0 - (2.0 / 3.0 + 1.0) / 2.0)).abs() < 1e-5,
            "{as_car}"
        );
        // Read as any other class: nothing lost.
        assert!(loss(hard(&[0, 0, 2, 4]), &target).abs() < 1e-6);
    }
}
