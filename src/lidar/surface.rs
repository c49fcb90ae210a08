//! Interpolation that never averages across a depth edge: the returns around a new pixel
//! are grouped by surface (by their measured depths and, optionally, by a guide depth such
//! as a decoded scene's completed depth), and only the target pixel's surface is blended.
//!
//! This module owns the grouping rule ([`SurfaceRule`], [`Guide`]); the fill of scattered
//! observations is [`super::scatter`], grid-to-grid resampling with the same rule
//! [`super::resample::resample_by_surface`].

/// When neighbouring returns count as one surface.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SurfaceRule {
    /// Largest |ln(d_a / d_b)| between two measured depths on one surface, per degree
    /// between their directions (a smooth surface changes depth in proportion to the angle:
    /// adjacent columns may differ little, beams several rows apart on the road a lot).
    pub jump_per_deg: f32,
    /// Largest |ln(g_t / g_k)| between the guide depth at the new pixel (g_t) and at a
    /// neighbour (g_k) for the guide to put them on one surface.
    pub guide_jump: f32,
    /// A split between two neighbours less than this many degrees apart is trusted as an
    /// edge: where the guide does not decide, the surface with the most weight is kept there
    /// rather than the blend. Adjacent columns of a 512-column scan are 0.7 deg apart, but
    /// beams 4 rows apart 1.7 deg, where a "jump" is often the road rising between beams.
    pub trust_below_deg: f32,
    /// Blend inverse depths within one surface (exact for planes along a line of
    /// directions: road, walls) rather than depths.
    pub inverse_depth: bool,
}

impl SurfaceRule {
    /// Plain interpolation: every neighbour is one surface.
    pub const ANY: SurfaceRule = SurfaceRule {
        jump_per_deg: f32::INFINITY,
        guide_jump: f32::INFINITY,
        trust_below_deg: 0.0,
        inverse_depth: false,
    };
}

impl Default for SurfaceRule {
    /// Tuned on KITTI training scans (never on the evaluation scans): BENCHMARKS.md,
    /// "Guided upsampling and restoration".
    fn default() -> Self {
        SurfaceRule {
            jump_per_deg: 0.3,
            guide_jump: 0.3,
            trust_below_deg: 1.0,
            inverse_depth: true,
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

/// A measured return next to a new pixel, with its interpolation weight, its direction (unit
/// vector) and the guide depth at it (0: none).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Neighbour {
    pub index: usize,
    pub depth: f32,
    pub weight: f32,
    pub direction: [f32; 3],
    pub guide: f32,
}

/// The angle between two unit vectors in degrees.
fn angle_deg(a: [f32; 3], b: [f32; 3]) -> f32 {
    let chord = ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt();
    (2.0 * (0.5 * chord).min(1.0).asin()).to_degrees()
}

/// Keeps the neighbours on the new pixel's surface and renormalises their weights to 1.
///
/// Surfaces: the neighbours sorted by measured depth, split wherever two consecutive depths
/// differ by more than `rule.jump_per_deg` times the angle between them (log depth). One
/// surface: every neighbour is kept. Across an edge, with a guide depth at the new pixel (`guide_target`)
/// and at the neighbours, each hypothesis, "the new pixel lies on surface S" and "it lies
/// between them" (everything blended), predicts the guide at the new pixel by blending the
/// neighbours' guide depths the same way; a single surface is kept when its prediction
/// beats the blend's by more than `rule.guide_jump` (log depth). Where the guide does not
/// decide (or there is none), the surface with the most weight is kept if a split is
/// trusted (`rule.trust_below_deg`), else the blend.
///
/// Returns whether what is kept is one surface (false: a blend across an edge).
pub(crate) fn keep_surface(ns: &mut Vec<Neighbour>, guide_target: f32, rule: &SurfaceRule) -> bool {
    if ns.len() < 2 {
        renormalise(ns);
        return true;
    }
    ns.sort_by(|a, b| a.depth.total_cmp(&b.depth));
    // Start index of each surface, and whether any split is a trusted edge.
    let mut starts = vec![0];
    let mut trusted = false;
    for i in 1..ns.len() {
        let pair = angle_deg(ns[i].direction, ns[i - 1].direction);
        if (ns[i].depth / ns[i - 1].depth).ln() > rule.jump_per_deg * pair {
            starts.push(i);
            trusted |= pair < rule.trust_below_deg;
        }
    }
    if starts.len() == 1 {
        renormalise(ns);
        return true;
    }
    let surface = |s: usize| {
        let end = starts.get(s + 1).copied().unwrap_or(ns.len());
        starts[s]..end
    };
    let weight = |r: std::ops::Range<usize>| ns[r].iter().map(|n| n.weight).sum::<f32>();
    let heaviest = || {
        (0..starts.len())
            .map(surface)
            .max_by(|a, b| weight(a.clone()).total_cmp(&weight(b.clone())))
    };
    let guided = guide_target > 0.0 && ns.iter().all(|n| n.guide > 0.0);
    let by_guide = if guided {
        // How far the guide blended over `r` lies from the guide at the new pixel.
        let miss = |r: std::ops::Range<usize>| {
            let w = weight(r.clone());
            let g = ns[r].iter().map(|n| n.weight * n.guide).sum::<f32>() / w;
            (g / guide_target).ln().abs()
        };
        let blend = miss(0..ns.len());
        (0..starts.len())
            .map(|s| (s, miss(surface(s))))
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .filter(|(_, m)| m + rule.guide_jump < blend)
            .map(|(s, _)| surface(s))
    } else {
        None
    };
    let chosen = by_guide.or_else(|| if trusted { heaviest() } else { None });
    let one = chosen.is_some();
    if let Some(r) = chosen {
        ns.truncate(r.end);
        ns.drain(..r.start);
    }
    renormalise(ns);
    one
}

pub(crate) fn renormalise(ns: &mut [Neighbour]) {
    let total: f32 = ns.iter().map(|n| n.weight).sum();
    for n in ns.iter_mut() {
        n.weight /= total;
    }
}

/// The weighted mean depth of `ns` (weights summing to 1), or with `inverse` the inverse of
/// the weighted mean inverse depth (exact for a plane along a line of directions; used
/// within one surface only, as across an edge it pulls towards the near side).
pub(crate) fn blend_depth(ns: &[Neighbour], inverse: bool) -> f32 {
    if inverse {
        1.0 / ns.iter().map(|n| n.weight / n.depth).sum::<f32>()
    } else {
        ns.iter().map(|n| n.weight * n.depth).sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Neighbours half a degree apart (edges between them are trusted).
    fn n(index: usize, depth: f32, weight: f32, guide: f32) -> Neighbour {
        let a = (0.5 * index as f32).to_radians();
        Neighbour {
            index,
            depth,
            weight,
            direction: [a.cos(), a.sin(), 0.0],
            guide,
        }
    }

    #[test]
    fn without_a_guide_the_nearest_return_picks_the_surface() {
        let mut ns = vec![
            n(0, 10.0, 0.6, 0.0),
            n(1, 10.5, 0.1, 0.0),
            n(2, 40.0, 0.3, 0.0),
        ];
        keep_surface(&mut ns, 0.0, &SurfaceRule::default());
        assert_eq!(ns.iter().map(|n| n.index).collect::<Vec<_>>(), vec![0, 1]);
        // A smooth slope (the road between two beams) is one surface.
        let mut ns = vec![n(0, 10.0, 0.5, 0.0), n(1, 11.0, 0.5, 0.0)];
        keep_surface(&mut ns, 0.0, &SurfaceRule::default());
        assert_eq!(blend_depth(&ns, false), 10.5);
        assert!((ns.iter().map(|n| n.weight).sum::<f32>() - 1.0).abs() < 1e-6);
        let d = blend_depth(&ns, false);
        assert!((10.0..=10.5).contains(&d), "{d}");
    }

    #[test]
    fn the_guide_picks_the_surface_even_against_the_nearest_return() {
        // The nearest return is on a wall at 10 m; the guide says the new pixel lies on
        // the road behind it (its depth agrees with the far neighbours').
        let mut ns = vec![
            n(0, 10.0, 0.6, 11.0),
            n(1, 41.0, 0.3, 39.0),
            n(2, 40.0, 0.1, 38.0),
        ];
        keep_surface(&mut ns, 38.5, &SurfaceRule::default());
        let mut kept: Vec<usize> = ns.iter().map(|n| n.index).collect();
        kept.sort();
        assert_eq!(kept, vec![1, 2]);
        let d = blend_depth(&ns, false);
        assert!((40.0..=41.0).contains(&d), "{d}");
        // A guide that lies between the surfaces (a blurred edge) keeps the blend where the
        // edge is not trusted (neighbours 4 deg apart).
        let mut ns = vec![n(0, 10.0, 0.5, 11.0), n(8, 40.0, 0.5, 39.0)];
        assert!(!keep_surface(&mut ns, 25.0, &SurfaceRule::default()));
        assert_eq!(ns.len(), 2);
        // With no opinion from the guide, the nearest return decides again.
        let mut ns = vec![n(0, 10.0, 0.6, 0.0), n(1, 41.0, 0.3, 0.0)];
        keep_surface(&mut ns, 38.5, &SurfaceRule::default());
        assert_eq!(ns.len(), 1);
        // An edge between neighbours far apart (beams several rows apart) is not trusted
        // without a guide: blended, as the road rising between beams looks the same.
        let mut ns = vec![n(0, 10.0, 0.6, 0.0), n(8, 41.0, 0.3, 0.0)];
        assert!(!keep_surface(&mut ns, 0.0, &SurfaceRule::default()));
        assert_eq!(ns[0].index, 0);
    }

    #[test]
    fn plain_rule_blends_everything() {
        let mut ns = vec![n(0, 10.0, 0.5, 0.0), n(1, 40.0, 0.5, 0.0)];
        keep_surface(&mut ns, 0.0, &SurfaceRule::ANY);
        assert_eq!(blend_depth(&ns, false), 25.0);
        assert_eq!(blend_depth(&ns, true), 16.0);
    }
}
