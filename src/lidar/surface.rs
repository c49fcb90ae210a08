//! Interpolation that never averages across a depth edge: the returns around a new pixel
//! are grouped by surface (by their measured depths and, optionally, by a guide depth such
//! as a decoded scene's completed depth), and only the target pixel's surface is blended.
//!
//! This module owns the grouping rule ([`SurfaceRule`], [`Guide`]) and the fill of
//! scattered observations on one grid ([`fill_scattered`]); grid-to-grid resampling with
//! the same rule is [`super::resample::resample_by_surface`].

/// When neighbouring returns count as one surface.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SurfaceRule {
    /// Largest |ln(d_a / d_b)| between two measured depths on one surface (0.1: 10 %).
    pub jump: f32,
    /// Largest |ln(g_t / g_k)| between the guide depth at the new pixel (g_t) and at a
    /// neighbour (g_k) for the guide to put them on one surface.
    pub guide_jump: f32,
    /// Blend inverse depths (exact for planes along a line of directions: road, walls)
    /// rather than depths.
    pub inverse_depth: bool,
}

impl SurfaceRule {
    /// Plain interpolation: every neighbour is one surface.
    pub const ANY: SurfaceRule = SurfaceRule {
        jump: f32::INFINITY,
        guide_jump: f32::INFINITY,
        inverse_depth: false,
    };
}

impl Default for SurfaceRule {
    /// Tuned on KITTI training scans (never on the evaluation scans): BENCHMARKS.md,
    /// "Guided upsampling and restoration".
    fn default() -> Self {
        SurfaceRule {
            jump: 0.1,
            guide_jump: 0.05,
            inverse_depth: false,
        }
    }
}

/// A depth image that tells which surface each pixel lies on (e.g. the decoded scene's
/// completed depth), at the new pixels (`target_m`) and at the observed ones (`source_m`);
/// 0 (or a missing entry) means "no opinion here".
#[derive(Debug, Clone, Copy)]
pub struct Guide<'a> {
    pub target_m: &'a [f32],
    pub source_m: &'a [f32],
}

impl Guide<'_> {
    fn at(values: &[f32], k: usize) -> f32 {
        values.get(k).copied().unwrap_or(0.0)
    }

    pub(crate) fn target(&self, k: usize) -> f32 {
        Self::at(self.target_m, k)
    }

    pub(crate) fn source(&self, k: usize) -> f32 {
        Self::at(self.source_m, k)
    }
}

/// A measured return next to a new pixel, with its interpolation weight and the guide
/// depth at it (0: none).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Neighbour {
    pub index: usize,
    pub depth: f32,
    pub weight: f32,
    pub guide: f32,
}

fn heaviest<'a>(ns: impl Iterator<Item = &'a Neighbour>) -> Option<&'a Neighbour> {
    ns.max_by(|a, b| a.weight.total_cmp(&b.weight))
}

/// Keeps the neighbours on the new pixel's surface and renormalises their weights to 1.
///
/// The reference return is the heaviest (nearest) one; with a guide depth `guide_target`,
/// it is the heaviest of those whose guide depth agrees with the new pixel's within
/// `rule.guide_jump` (or, if none does, of those that agree best). Kept: every neighbour
/// whose measured depth lies within `rule.jump` of the reference's.
pub(crate) fn keep_surface(ns: &mut Vec<Neighbour>, guide_target: f32, rule: &SurfaceRule) {
    let disagreement = |n: &Neighbour| {
        if guide_target > 0.0 && n.guide > 0.0 {
            (n.guide / guide_target).ln().abs()
        } else {
            f32::INFINITY
        }
    };
    let best = ns.iter().map(disagreement).fold(f32::INFINITY, f32::min);
    let reference = if best.is_finite() {
        let limit = best.max(rule.guide_jump);
        heaviest(ns.iter().filter(|n| disagreement(n) <= limit))
    } else {
        heaviest(ns.iter())
    };
    let Some(reference) = reference.map(|n| n.depth) else {
        return;
    };
    ns.retain(|n| (n.depth / reference).ln().abs() <= rule.jump);
    renormalise(ns);
}

fn renormalise(ns: &mut [Neighbour]) {
    let total: f32 = ns.iter().map(|n| n.weight).sum();
    for n in ns.iter_mut() {
        n.weight /= total;
    }
}

/// The weighted mean depth of `ns` (weights summing to 1), or with `inverse` the inverse of
/// the weighted mean inverse depth.
pub(crate) fn blend_depth(ns: &[Neighbour], inverse: bool) -> f32 {
    if inverse {
        1.0 / ns.iter().map(|n| n.weight / n.depth).sum::<f32>()
    } else {
        ns.iter().map(|n| n.weight * n.depth).sum()
    }
}

/// How [`fill_scattered`] estimates an unobserved pixel.
#[derive(Debug, Clone, Copy)]
pub enum ScatterFill<'a> {
    /// The nearest observed pixel.
    Nearest,
    /// Inverse-distance weighting restricted to one surface by `rule` (optionally guided by
    /// `guide`, a depth on the same grid), over that surface's observed pixels within
    /// twice the distance of its nearest one. [`SurfaceRule::ANY`] without a guide is
    /// plain IDW.
    Idw {
        rule: SurfaceRule,
        guide: Option<&'a [f32]>,
    },
}

/// How far (in pixels) [`fill_scattered`] looks for observed pixels.
pub const SCATTER_RADIUS: isize = 8;

/// Fills a `height x width` grid (row-major, columns circular) from a scattered observation
/// (meters, 0 = not observed): observed pixels keep their depth exactly, other pixels are
/// estimated from the observed ones within [`SCATTER_RADIUS`] and stay 0 where there are
/// none.
pub fn fill_scattered(observed: &[f32], height: usize, width: usize, how: ScatterFill) -> Vec<f32> {
    let mut out = vec![0.0f32; height * width];
    if observed.len() != height * width || width == 0 {
        return out;
    }
    let mut ns: Vec<Neighbour> = Vec::new();
    let r = SCATTER_RADIUS;
    for i in 0..height as isize {
        for j in 0..width as isize {
            let k = i as usize * width + j as usize;
            if observed[k] > 0.0 {
                out[k] = observed[k];
                continue;
            }
            ns.clear();
            for ii in (i - r).max(0)..(i + r + 1).min(height as isize) {
                for dj in -r..=r {
                    let jj = (j + dj).rem_euclid(width as isize) as usize;
                    let idx = ii as usize * width + jj;
                    if observed[idx] > 0.0 {
                        let di = ii - i;
                        ns.push(Neighbour {
                            index: idx,
                            depth: observed[idx],
                            // Distance in pixels until the IDW step below.
                            weight: ((di * di + dj * dj) as f32).sqrt(),
                            guide: 0.0,
                        });
                    }
                }
            }
            let Some(nearest) = ns.iter().min_by(|a, b| a.weight.total_cmp(&b.weight)).copied()
            else {
                continue;
            };
            out[k] = match how {
                ScatterFill::Nearest => nearest.depth,
                ScatterFill::Idw { rule, guide } => {
                    let g = |idx: usize| guide.and_then(|g| g.get(idx)).copied().unwrap_or(0.0);
                    for n in ns.iter_mut() {
                        n.weight = 1.0 / n.weight.max(0.5);
                        n.guide = g(n.index);
                    }
                    keep_surface(&mut ns, g(k), &rule);
                    // Within twice the distance of the surface's nearest return.
                    let reach = ns.iter().map(|n| n.weight).fold(0.0, f32::max) * 0.5;
                    ns.retain(|n| n.weight >= reach);
                    renormalise(&mut ns);
                    blend_depth(&ns, rule.inverse_depth)
                }
            };
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn n(index: usize, depth: f32, weight: f32, guide: f32) -> Neighbour {
        Neighbour {
            index,
            depth,
            weight,
            guide,
        }
    }

    #[test]
    fn without_a_guide_the_nearest_return_picks_the_surface() {
        let mut ns = vec![n(0, 10.0, 0.6, 0.0), n(1, 10.5, 0.1, 0.0), n(2, 40.0, 0.3, 0.0)];
        keep_surface(&mut ns, 0.0, &SurfaceRule::default());
        assert_eq!(ns.iter().map(|n| n.index).collect::<Vec<_>>(), vec![0, 1]);
        assert!((ns.iter().map(|n| n.weight).sum::<f32>() - 1.0).abs() < 1e-6);
        let d = blend_depth(&ns, false);
        assert!((10.0..=10.5).contains(&d), "{d}");
    }

    #[test]
    fn the_guide_picks_the_surface_even_against_the_nearest_return() {
        // The nearest return is on a wall at 10 m; the guide says the new pixel lies on
        // the road behind it (its depth agrees with the far neighbours').
        let mut ns = vec![n(0, 10.0, 0.6, 11.0), n(1, 41.0, 0.3, 39.0), n(2, 40.0, 0.1, 38.0)];
        keep_surface(&mut ns, 38.5, &SurfaceRule::default());
        let kept: Vec<usize> = ns.iter().map(|n| n.index).collect();
        assert_eq!(kept, vec![1, 2]);
        let d = blend_depth(&ns, false);
        assert!((40.0..=41.0).contains(&d), "{d}");
        // With no opinion from the guide, the nearest return decides again.
        let mut ns = vec![n(0, 10.0, 0.6, 0.0), n(1, 41.0, 0.3, 0.0)];
        keep_surface(&mut ns, 38.5, &SurfaceRule::default());
        assert_eq!(ns.len(), 1);
        assert_eq!(ns[0].index, 0);
    }

    #[test]
    fn plain_rule_blends_everything() {
        let mut ns = vec![n(0, 10.0, 0.5, 0.0), n(1, 40.0, 0.5, 0.0)];
        keep_surface(&mut ns, 0.0, &SurfaceRule::ANY);
        assert_eq!(blend_depth(&ns, false), 25.0);
        assert_eq!(blend_depth(&ns, true), 16.0);
    }

    /// 16 x 64 grid: a wall at 10 m on the left half, 40 m on the right; 10 % observed.
    fn scattered_edge() -> (Vec<f32>, Vec<f32>) {
        let (h, w) = (16, 64);
        let truth: Vec<f32> = (0..h * w)
            .map(|k| if k % w < 32 { 10.0 } else { 40.0 })
            .collect();
        let observed = (0..h * w)
            .map(|k| if (k * 7919) % 10 == 0 { truth[k] } else { 0.0 })
            .collect();
        (truth, observed)
    }

    #[test]
    fn scattered_fill_keeps_returns_and_never_averages_across_the_edge() {
        let (truth, observed) = scattered_edge();
        let (h, w) = (16, 64);
        let plain = fill_scattered(
            &observed,
            h,
            w,
            ScatterFill::Idw {
                rule: SurfaceRule::ANY,
                guide: None,
            },
        );
        assert!(
            plain.iter().any(|d| *d > 11.0 && *d < 39.0),
            "plain IDW smears the edge"
        );
        for guide in [None, Some(truth.as_slice())] {
            let out = fill_scattered(
                &observed,
                h,
                w,
                ScatterFill::Idw {
                    rule: SurfaceRule::default(),
                    guide,
                },
            );
            for k in 0..h * w {
                if observed[k] > 0.0 {
                    assert_eq!(out[k].to_bits(), observed[k].to_bits(), "return {k} kept");
                }
                assert!(out[k] == 10.0 || out[k] == 40.0, "pixel {k}: {}", out[k]);
            }
            // With the true surfaces as guide, every pixel lands on its own surface.
            if guide.is_some() {
                assert_eq!(out, truth);
            }
        }
    }
}
