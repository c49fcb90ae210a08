//! What the analytic ray caster hits: surfaces (class, material, reflectivity) and the
//! primitives (axis-aligned boxes, vertical cylinders, spheres) with their ray hits.

use rangegan_mcap::sim::Material;

/// What a surface is: class, material, diffuse reflectivity.
#[derive(Debug, Clone, Copy)]
pub(super) struct Surface {
    pub(super) label: u32,
    pub(super) material: Material,
    pub(super) reflectivity: f32,
}

pub(super) const fn surf(label: u32, material: Material, reflectivity: f32) -> Surface {
    Surface {
        label,
        material,
        reflectivity,
    }
}

#[derive(Debug, Clone, Copy)]
pub(super) enum Shape {
    /// Axis-aligned box.
    Box {
        min: [f32; 3],
        max: [f32; 3],
    },
    /// Vertical cylinder.
    Cylinder {
        c: [f32; 2],
        r: f32,
        z0: f32,
        z1: f32,
    },
    Sphere {
        c: [f32; 3],
        r: f32,
    },
}

#[derive(Debug, Clone, Copy)]
pub(super) struct Object {
    pub(super) shape: Shape,
    pub(super) surface: Surface,
}

impl Object {
    /// Centre and radius of the footprint in the ground plane (for culling).
    pub(super) fn footprint(&self) -> ([f32; 2], f32) {
        match self.shape {
            Shape::Box { min, max } => {
                let c = [(min[0] + max[0]) / 2.0, (min[1] + max[1]) / 2.0];
                let r = ((max[0] - min[0]).powi(2) + (max[1] - min[1]).powi(2)).sqrt() / 2.0;
                (c, r)
            }
            Shape::Cylinder { c, r, .. } => (c, r),
            Shape::Sphere { c, r } => ([c[0], c[1]], r),
        }
    }

    /// Nearest hit distance and outward normal of ray `o + t d`, t > 0.
    pub(super) fn hit(&self, o: [f32; 3], d: [f32; 3]) -> Option<(f32, [f32; 3])> {
        match self.shape {
            Shape::Box { min, max } => {
                let (mut t0, mut t1, mut axis) = (0.0f32, f32::INFINITY, 3usize);
                for a in 0..3 {
                    if d[a].abs() < 1e-9 {
                        if o[a] < min[a] || o[a] > max[a] {
                            return None;
                        }
                        continue;
                    }
                    let (mut ta, mut tb) = ((min[a] - o[a]) / d[a], (max[a] - o[a]) / d[a]);
                    if ta > tb {
                        std::mem::swap(&mut ta, &mut tb);
                    }
                    if ta > t0 {
                        t0 = ta;
                        axis = a;
                    }
                    t1 = t1.min(tb);
                    if t0 > t1 {
                        return None;
                    }
                }
                if axis == 3 {
                    return None; // origin inside
                }
                let mut n = [0.0; 3];
                n[axis] = -d[axis].signum();
                Some((t0, n))
            }
            Shape::Cylinder { c, r, z0, z1 } => {
                let (px, py) = (o[0] - c[0], o[1] - c[1]);
                let a = d[0] * d[0] + d[1] * d[1];
                if a < 1e-12 {
                    return None;
                }
                let b = px * d[0] + py * d[1];
                let disc = b * b - a * (px * px + py * py - r * r);
                if disc < 0.0 {
                    return None;
                }
                let t = (-b - disc.sqrt()) / a;
                let z = o[2] + t * d[2];
                (t > 0.0 && z >= z0 && z <= z1).then(|| {
                    let (nx, ny) = (px + t * d[0], py + t * d[1]);
                    (t, [nx / r, ny / r, 0.0])
                })
            }
            Shape::Sphere { c, r } => {
                let p = [o[0] - c[0], o[1] - c[1], o[2] - c[2]];
                let b = p[0] * d[0] + p[1] * d[1] + p[2] * d[2];
                let disc = b * b - (p[0] * p[0] + p[1] * p[1] + p[2] * p[2] - r * r);
                if disc < 0.0 {
                    return None;
                }
                let t = -b - disc.sqrt();
                (t > 0.0).then(|| {
                    let q = [p[0] + t * d[0], p[1] + t * d[1], p[2] + t * d[2]];
                    (t, [q[0] / r, q[1] / r, q[2] / r])
                })
            }
        }
    }
}
