//! Bounding-volume hierarchy over scene primitives: binned surface-area
//! heuristic build, flat node array, ordered stack traversal for the nearest hit.

use super::geometry::{Aabb, Primitive, Ray, ShapeHit, Vec3};

const LEAF_SIZE: usize = 4;
const BINS: usize = 12;

#[derive(Debug, Clone, Copy)]
struct Node {
    bounds: Aabb,
    /// Leaf: first primitive; inner: index of the right child (left is `self + 1`).
    offset: u32,
    /// Primitives in a leaf; 0 for inner nodes.
    count: u16,
    axis: u16,
}

/// A BVH owning its primitives (reordered for locality).
#[derive(Debug, Clone, Default)]
pub struct Bvh {
    nodes: Vec<Node>,
    pub prims: Vec<Primitive>,
}

/// The nearest hit found by [`Bvh::nearest`]: which primitive and where.
#[derive(Debug, Clone, Copy)]
pub struct BvhHit {
    pub prim: u32,
    pub hit: ShapeHit,
}

impl Bvh {
    pub fn build(prims: Vec<Primitive>) -> Self {
        if prims.is_empty() {
            return Bvh::default();
        }
        let bounds: Vec<Aabb> = prims.iter().map(|p| p.shape.bounds()).collect();
        let centres: Vec<Vec3> = bounds.iter().map(Aabb::centre).collect();
        let mut order: Vec<u32> = (0..prims.len() as u32).collect();
        let mut nodes = Vec::with_capacity(2 * prims.len() / LEAF_SIZE + 1);
        build_node(&mut nodes, &mut order, 0, &bounds, &centres);
        let prims = order.iter().map(|&i| prims[i as usize]).collect();
        Bvh { nodes, prims }
    }

    pub fn is_empty(&self) -> bool {
        self.prims.is_empty()
    }

    /// Nearest accepted hit with `t` in (`t_min`, `t_max`). `accept` may veto a hit
    /// or move it further along the ray (volumetric media), returning its distance.
    #[inline]
    pub fn nearest(
        &self,
        ray: &Ray,
        t_min: f32,
        mut t_max: f32,
        mut accept: impl FnMut(u32, &ShapeHit) -> Option<f32>,
    ) -> Option<BvhHit> {
        if self.nodes.is_empty() {
            return None;
        }
        let mut best: Option<BvhHit> = None;
        self.nodes[0].bounds.hit(ray, t_max)?;
        // Stack of (node, entry distance); children are tested at their parent so
        // the nearer one is visited first and a missed box is never pushed.
        let mut stack = [(0u32, 0f32); 128];
        let mut sp = 0usize;
        let mut node_idx = 0u32;
        loop {
            let node = &self.nodes[node_idx as usize];
            if node.count > 0 {
                let first = node.offset as usize;
                for i in first..first + node.count as usize {
                    let Some(h) = self.prims[i].shape.intersect(ray, t_min, t_max) else {
                        continue;
                    };
                    if let Some(t) = accept(i as u32, &h).filter(|&t| t < t_max) {
                        t_max = t;
                        best = Some(BvhHit {
                            prim: i as u32,
                            hit: ShapeHit { t, ..h },
                        });
                    }
                }
            } else {
                let (l, r) = (node_idx + 1, node.offset);
                let tl = self.nodes[l as usize].bounds.hit(ray, t_max);
                let tr = self.nodes[r as usize].bounds.hit(ray, t_max);
                match (tl, tr) {
                    (Some(a), Some(b)) => {
                        let (near, far, t_far) = if a <= b { (l, r, b) } else { (r, l, a) };
                        if sp < stack.len() {
                            stack[sp] = (far, t_far);
                            sp += 1;
                        }
                        node_idx = near;
                        continue;
                    }
                    (Some(_), None) => {
                        node_idx = l;
                        continue;
                    }
                    (None, Some(_)) => {
                        node_idx = r;
                        continue;
                    }
                    (None, None) => {}
                }
            }
            // Pop the next node still nearer than the best hit so far.
            loop {
                if sp == 0 {
                    return best;
                }
                sp -= 1;
                if stack[sp].1 < t_max {
                    break;
                }
            }
            node_idx = stack[sp].0;
        }
    }
}

fn build_node(
    nodes: &mut Vec<Node>,
    order: &mut [u32],
    first: usize,
    bounds: &[Aabb],
    centres: &[Vec3],
) -> usize {
    let node_bounds = order
        .iter()
        .fold(Aabb::EMPTY, |b, &i| b.union(bounds[i as usize]));
    let idx = nodes.len();
    nodes.push(Node {
        bounds: node_bounds,
        offset: first as u32,
        count: order.len() as u16,
        axis: 0,
    });
    if order.len() <= LEAF_SIZE {
        return idx;
    }
    let cb = order
        .iter()
        .fold(Aabb::EMPTY, |b, &i| b.grow(centres[i as usize]));
    let extent = cb.max - cb.min;
    let axis = if extent.x >= extent.y && extent.x >= extent.z {
        0
    } else if extent.y >= extent.z {
        1
    } else {
        2
    };
    let (lo, span) = (cb.min.axis(axis), extent.axis(axis));
    let mid = if span <= 1e-9 {
        order.len() / 2
    } else {
        // Binned SAH along the widest centroid axis.
        let bin_of = |i: u32| {
            (((centres[i as usize].axis(axis) - lo) / span * BINS as f32) as usize).min(BINS - 1)
        };
        let mut bin_bounds = [Aabb::EMPTY; BINS];
        let mut bin_count = [0usize; BINS];
        for &i in order.iter() {
            let b = bin_of(i);
            bin_bounds[b] = bin_bounds[b].union(bounds[i as usize]);
            bin_count[b] += 1;
        }
        let mut best = (f32::INFINITY, 0usize);
        for split in 1..BINS {
            let (mut lb, mut rb, mut ln, mut rn) = (Aabb::EMPTY, Aabb::EMPTY, 0, 0);
            for b in 0..split {
                lb = lb.union(bin_bounds[b]);
                ln += bin_count[b];
            }
            for b in split..BINS {
                rb = rb.union(bin_bounds[b]);
                rn += bin_count[b];
            }
            if ln == 0 || rn == 0 {
                continue;
            }
            let cost = lb.surface_area() * ln as f32 + rb.surface_area() * rn as f32;
            if cost < best.0 {
                best = (cost, split);
            }
        }
        if best.0.is_finite() {
            let split = best.1;
            let mut l = 0;
            for k in 0..order.len() {
                if bin_of(order[k]) < split {
                    order.swap(k, l);
                    l += 1;
                }
            }
            l
        } else {
            order.len() / 2
        }
    };
    let mid = if mid == 0 || mid == order.len() {
        order.sort_by(|&a, &b| {
            centres[a as usize]
                .axis(axis)
                .total_cmp(&centres[b as usize].axis(axis))
        });
        order.len() / 2
    } else {
        mid
    };
    let (left, right) = order.split_at_mut(mid);
    build_node(nodes, left, first, bounds, centres);
    let right_idx = build_node(nodes, right, first + mid, bounds, centres);
    nodes[idx].offset = right_idx as u32;
    nodes[idx].count = 0;
    nodes[idx].axis = axis as u16;
    idx
}

#[cfg(test)]
mod tests {
    use super::super::geometry::{Shape, v3};
    use super::*;
    use crate::util::rng::Rng;

    #[test]
    fn bvh_finds_the_same_nearest_hit_as_brute_force() {
        let mut rng = Rng::keyed(1, 0);
        let prims: Vec<Primitive> = (0..2000)
            .map(|k| {
                let c = v3(
                    rng.range(-50.0, 50.0),
                    rng.range(-50.0, 50.0),
                    rng.range(-5.0, 5.0),
                );
                let shape = match k % 3 {
                    0 => Shape::triangle(
                        c,
                        c + v3(rng.range(-2.0, 2.0), 1.0, 0.0),
                        c + v3(0.0, rng.range(-2.0, 2.0), 2.0),
                    ),
                    1 => Shape::Ellipsoid {
                        centre: c,
                        radii: v3(1.0, 0.5, 2.0),
                    },
                    _ => Shape::Cylinder {
                        base: c,
                        radius: 0.3,
                        height: 3.0,
                    },
                };
                Primitive {
                    shape,
                    surface: 0,
                    instance: k as u16,
                }
            })
            .collect();
        let bvh = Bvh::build(prims.clone());
        for k in 0..500 {
            let a = k as f32 * 0.0127;
            let ray = Ray::new(
                v3(0.0, 0.0, 0.5),
                v3(a.cos(), a.sin(), rng.range(-0.1, 0.1)).normalized(),
            );
            let brute = prims
                .iter()
                .filter_map(|p| {
                    p.shape
                        .intersect(&ray, 0.0, 200.0)
                        .map(|h| (h.t, p.instance))
                })
                .min_by(|a, b| a.0.total_cmp(&b.0));
            let fast = bvh
                .nearest(&ray, 0.0, 200.0, |_, h| Some(h.t))
                .map(|h| (h.hit.t, bvh.prims[h.prim as usize].instance));
            assert_eq!(brute, fast, "ray {k}");
        }
    }
}
