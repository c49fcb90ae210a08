//! Holes in a range image (pixels without a return): how far each lies from the nearest
//! return, and holes of known kinds cut into a scan whose truth is known (how completion
//! of dropped rays is trained and scored). Images are row-major `height x width`, 0 = no
//! return; columns wrap around (a full revolution).

use std::collections::{HashSet, VecDeque};

use crate::util::rng::Rng;

/// The 4-neighbours of pixel `k` on a `height x width` image: the pixels above and below
/// (where there are rows) and left and right (columns wrap around).
pub fn neighbours(k: usize, height: usize, width: usize) -> impl Iterator<Item = usize> {
    let (i, j) = (k / width, k % width);
    [
        (i > 0).then(|| k - width),
        (i + 1 < height).then(|| k + width),
        Some(i * width + (j + width - 1) % width),
        Some(i * width + (j + 1) % width),
    ]
    .into_iter()
    .flatten()
}

/// Steps (4-neighbour, columns wrapping around) from every pixel to the nearest pixel
/// with a return: 0 on a return, `u32::MAX` when the image has none.
pub fn distance_to_returns(observed: &[f32], height: usize, width: usize) -> Vec<u32> {
    let mut distance = vec![u32::MAX; observed.len()];
    if observed.len() != height * width || width == 0 {
        return distance;
    }
    let mut queue = VecDeque::new();
    for (k, &d) in observed.iter().enumerate() {
        if d > 0.0 {
            distance[k] = 0;
            queue.push_back(k);
        }
    }
    while let Some(k) = queue.pop_front() {
        let next = distance[k] + 1;
        for q in neighbours(k, height, width) {
            if distance[q] > next {
                distance[q] = next;
                queue.push_back(q);
            }
        }
    }
    distance
}

/// A kind of hole cut into a scan. Sizes are for a 64-beam sensor at 512 columns (a column
/// 0.70 deg, a beam ~0.4 deg), scaled with the columns of other grids.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum HoleKind {
    /// Single pixels, 5 % of the image.
    Pixels,
    /// 150 patches of 2 beams x 1.5 deg.
    Small,
    /// 40 patches of 6 beams x 4 deg.
    Medium,
    /// 8 patches of 16 beams x 20 deg.
    Large,
    /// 4 whole beams.
    Beams,
    /// A 30 deg sector of every beam.
    Sector,
    /// Object-shaped: connected surfaces within 25 m that stand in front of what is beside
    /// them, 30-600 pixels each, until about 8 % of the returns are removed.
    Objects,
}

impl HoleKind {
    pub const ALL: [HoleKind; 7] = [
        HoleKind::Pixels,
        HoleKind::Small,
        HoleKind::Medium,
        HoleKind::Large,
        HoleKind::Beams,
        HoleKind::Sector,
        HoleKind::Objects,
    ];

    pub fn name(self) -> &'static str {
        match self {
            HoleKind::Pixels => "pixels",
            HoleKind::Small => "small",
            HoleKind::Medium => "medium",
            HoleKind::Large => "large",
            HoleKind::Beams => "beams",
            HoleKind::Sector => "sector",
            HoleKind::Objects => "objects",
        }
    }

    pub fn parse(name: &str) -> Option<HoleKind> {
        Self::ALL.into_iter().find(|k| k.name() == name)
    }

    /// The pixels of holes of this kind in `range_m` (`height x width`), drawn with `rng`.
    pub fn cut(self, range_m: &[f32], height: usize, width: usize, rng: &mut Rng) -> Vec<bool> {
        let (h, w) = (height, width);
        let mut mask = vec![false; h * w];
        let cols = |at_512: usize| (at_512 * w).div_ceil(512).max(1);
        let mut patch = |rows: usize, columns: usize, count: usize, rng: &mut Rng| {
            for _ in 0..count {
                let (i0, j0) = (rng.below(h.saturating_sub(rows) + 1), rng.below(w));
                for i in i0..(i0 + rows).min(h) {
                    for j in j0..j0 + columns {
                        mask[i * w + j % w] = true;
                    }
                }
            }
        };
        match self {
            HoleKind::Pixels => mask.iter_mut().for_each(|m| *m = rng.below(20) == 0),
            HoleKind::Small => patch(2, cols(2), 150, rng),
            HoleKind::Medium => patch(6, cols(6), 40, rng),
            HoleKind::Large => patch(16, cols(28), 8, rng),
            HoleKind::Beams => {
                for _ in 0..4 {
                    let i = rng.below(h);
                    mask[i * w..(i + 1) * w].fill(true);
                }
            }
            HoleKind::Sector => patch(h, cols(43), 1, rng),
            HoleKind::Objects => objects(range_m, h, w, rng, &mut mask),
        }
        mask
    }
}

/// Marks object-shaped holes ([`HoleKind::Objects`]) in `mask`.
fn objects(r: &[f32], h: usize, w: usize, rng: &mut Rng, mask: &mut [bool]) {
    let target = r.iter().filter(|&&d| d > 0.0).count() / 12;
    let mut removed = 0;
    for _ in 0..400 {
        if removed >= target {
            break;
        }
        let seed = rng.below(h * w);
        if r[seed] <= 0.0 || r[seed] > 25.0 || mask[seed] {
            continue;
        }
        let mut region = vec![seed];
        let mut seen = HashSet::from([seed]);
        let (mut k, mut border, mut nearer_than_border) = (0, 0usize, 0usize);
        while k < region.len() && region.len() < 600 {
            let p = region[k];
            k += 1;
            for q in neighbours(p, h, w) {
                if seen.contains(&q) {
                    continue;
                }
                if r[q] > 0.0 && (r[q] - r[p]).abs() < 0.03 * r[p] {
                    seen.insert(q);
                    region.push(q);
                } else if r[q] > 0.0 {
                    border += 1;
                    nearer_than_border += usize::from(r[q] > r[p]);
                }
            }
        }
        let in_front = border > 0 && nearer_than_border * 2 > border;
        if (30..600).contains(&region.len()) && in_front {
            removed += region.len();
            for p in region {
                mask[p] = true;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn holes_of_each_kind_have_their_size() {
        let (h, w) = (64, 512);
        // A wall at 10 m with a post at 5 m in front of it.
        let range: Vec<f32> = (0..h * w)
            .map(|k| {
                if (100..110).contains(&(k % w)) {
                    5.0
                } else {
                    10.0
                }
            })
            .collect();
        let count = |kind: HoleKind| {
            let m = kind.cut(&range, h, w, &mut Rng::new(3));
            m.iter().filter(|&&m| m).count()
        };
        let pixels = count(HoleKind::Pixels) as f32 / (h * w) as f32;
        assert!((pixels - 0.05).abs() < 0.01, "{pixels}");
        assert_eq!(count(HoleKind::Beams) % w, 0);
        assert!(count(HoleKind::Beams) >= w && count(HoleKind::Beams) <= 4 * w);
        assert_eq!(count(HoleKind::Sector), h * 43);
        assert!(count(HoleKind::Large) <= 8 * 16 * 28 && count(HoleKind::Large) > 16 * 28);
        // Only the post stands in front of its surroundings; it is 640 pixels, too big,
        // so no object hole is cut; a shorter post is.
        assert_eq!(count(HoleKind::Objects), 0);
        let short: Vec<f32> = (0..h * w)
            .map(|k| {
                let (i, j) = (k / w, k % w);
                if (100..110).contains(&j) && i >= 40 {
                    5.0
                } else {
                    10.0
                }
            })
            .collect();
        let m = HoleKind::Objects.cut(&short, h, w, &mut Rng::new(3));
        let cut: Vec<usize> = (0..h * w).filter(|&k| m[k]).collect();
        assert_eq!(cut.len(), 240, "the post is removed whole");
        assert!(cut.iter().all(|&k| short[k] == 5.0));
        for kind in HoleKind::ALL {
            assert_eq!(HoleKind::parse(kind.name()), Some(kind));
        }
    }

    #[test]
    fn distance_counts_steps_and_wraps_around_the_columns() {
        // 2 x 5, one return at (0, 0).
        let mut observed = vec![0.0; 10];
        observed[0] = 5.0;
        let d = distance_to_returns(&observed, 2, 5);
        assert_eq!(d, vec![0, 1, 2, 2, 1, 1, 2, 3, 3, 2]);
        assert!(
            distance_to_returns(&[0.0; 4], 2, 2)
                .iter()
                .all(|&d| d == u32::MAX)
        );
    }
}
