//! Geometry for ray casting: a small 3-vector, axis-aligned boxes, and the
//! scene primitives (triangles, axis-aligned ellipsoids, vertical cylinders) with
//! their ray intersections. Knows nothing about labels or materials beyond the
//! surface index each primitive carries.

use std::ops::{Add, Mul, Neg, Sub};

/// A 3-vector in meters (or a direction), f32.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Vec3 {
    pub x: f32,
    pub y: f32,
    pub z: f32,
}

#[inline]
pub const fn v3(x: f32, y: f32, z: f32) -> Vec3 {
    Vec3 { x, y, z }
}

impl Vec3 {
    #[inline]
    pub fn dot(self, o: Vec3) -> f32 {
        self.x * o.x + self.y * o.y + self.z * o.z
    }
    #[inline]
    pub fn cross(self, o: Vec3) -> Vec3 {
        v3(
            self.y * o.z - self.z * o.y,
            self.z * o.x - self.x * o.z,
            self.x * o.y - self.y * o.x,
        )
    }
    #[inline]
    pub fn length(self) -> f32 {
        self.dot(self).sqrt()
    }
    #[inline]
    pub fn normalized(self) -> Vec3 {
        let l = self.length();
        if l > 0.0 { self * (1.0 / l) } else { self }
    }
    #[inline]
    pub fn min(self, o: Vec3) -> Vec3 {
        v3(self.x.min(o.x), self.y.min(o.y), self.z.min(o.z))
    }
    #[inline]
    pub fn max(self, o: Vec3) -> Vec3 {
        v3(self.x.max(o.x), self.y.max(o.y), self.z.max(o.z))
    }
    #[inline]
    pub fn axis(self, a: usize) -> f32 {
        match a {
            0 => self.x,
            1 => self.y,
            _ => self.z,
        }
    }
    #[inline]
    pub fn mul_elem(self, o: Vec3) -> Vec3 {
        v3(self.x * o.x, self.y * o.y, self.z * o.z)
    }
    pub fn to_array(self) -> [f32; 3] {
        [self.x, self.y, self.z]
    }
}

impl Add for Vec3 {
    type Output = Vec3;
    #[inline]
    fn add(self, o: Vec3) -> Vec3 {
        v3(self.x + o.x, self.y + o.y, self.z + o.z)
    }
}
impl Sub for Vec3 {
    type Output = Vec3;
    #[inline]
    fn sub(self, o: Vec3) -> Vec3 {
        v3(self.x - o.x, self.y - o.y, self.z - o.z)
    }
}
impl Mul<f32> for Vec3 {
    type Output = Vec3;
    #[inline]
    fn mul(self, s: f32) -> Vec3 {
        v3(self.x * s, self.y * s, self.z * s)
    }
}
impl Neg for Vec3 {
    type Output = Vec3;
    #[inline]
    fn neg(self) -> Vec3 {
        v3(-self.x, -self.y, -self.z)
    }
}

/// A ray with its precomputed inverse direction (for slab tests).
#[derive(Debug, Clone, Copy)]
pub struct Ray {
    pub origin: Vec3,
    pub dir: Vec3,
    pub inv_dir: Vec3,
}

impl Ray {
    pub fn new(origin: Vec3, dir: Vec3) -> Self {
        Ray {
            origin,
            dir,
            inv_dir: v3(1.0 / dir.x, 1.0 / dir.y, 1.0 / dir.z),
        }
    }
    #[inline]
    pub fn at(&self, t: f32) -> Vec3 {
        self.origin + self.dir * t
    }
}

/// Axis-aligned bounding box.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Aabb {
    pub min: Vec3,
    pub max: Vec3,
}

impl Aabb {
    pub const EMPTY: Aabb = Aabb {
        min: v3(f32::INFINITY, f32::INFINITY, f32::INFINITY),
        max: v3(f32::NEG_INFINITY, f32::NEG_INFINITY, f32::NEG_INFINITY),
    };

    #[inline]
    pub fn union(self, o: Aabb) -> Aabb {
        Aabb {
            min: self.min.min(o.min),
            max: self.max.max(o.max),
        }
    }
    #[inline]
    pub fn grow(self, p: Vec3) -> Aabb {
        Aabb {
            min: self.min.min(p),
            max: self.max.max(p),
        }
    }
    pub fn centre(&self) -> Vec3 {
        (self.min + self.max) * 0.5
    }
    pub fn surface_area(&self) -> f32 {
        let d = self.max - self.min;
        if d.x < 0.0 {
            0.0
        } else {
            2.0 * (d.x * d.y + d.y * d.z + d.z * d.x)
        }
    }
    /// Entry distance of `ray` into the box if it enters before `t_max`.
    #[inline]
    pub fn hit(&self, ray: &Ray, t_max: f32) -> Option<f32> {
        let t1 = (self.min - ray.origin).mul_elem(ray.inv_dir);
        let t2 = (self.max - ray.origin).mul_elem(ray.inv_dir);
        let tmin =
            t1.x.min(t2.x)
                .max(t1.y.min(t2.y))
                .max(t1.z.min(t2.z))
                .max(0.0);
        let tmax =
            t1.x.max(t2.x)
                .min(t1.y.max(t2.y))
                .min(t1.z.max(t2.z))
                .min(t_max);
        (tmin <= tmax).then_some(tmin)
    }
}

/// What a primitive is made of, shape-wise.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Shape {
    /// Triangle stored as a vertex and two edges (Moller-Trumbore).
    Triangle { p0: Vec3, e1: Vec3, e2: Vec3 },
    /// Axis-aligned ellipsoid (tree crowns, bushes, heads).
    Ellipsoid { centre: Vec3, radii: Vec3 },
    /// Vertical capped cylinder (poles, trunks, bodies).
    Cylinder {
        base: Vec3,
        radius: f32,
        height: f32,
    },
}

/// One primitive of a scene: a shape, the surface it shows, and its instance.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Primitive {
    pub shape: Shape,
    /// Index into the scene's surface table.
    pub surface: u16,
    /// Object instance id (0 = stuff, not an object).
    pub instance: u16,
}

/// A ray-primitive intersection: distance along the (unit) ray, and the surface
/// normal there (not oriented towards the ray), plus the exit distance for closed
/// shapes (used for volumetric vegetation).
#[derive(Debug, Clone, Copy)]
pub struct ShapeHit {
    pub t: f32,
    pub t_exit: f32,
    pub normal: Vec3,
}

impl Shape {
    pub fn triangle(a: Vec3, b: Vec3, c: Vec3) -> Shape {
        Shape::Triangle {
            p0: a,
            e1: b - a,
            e2: c - a,
        }
    }

    pub fn bounds(&self) -> Aabb {
        match *self {
            Shape::Triangle { p0, e1, e2 } => Aabb::EMPTY.grow(p0).grow(p0 + e1).grow(p0 + e2),
            Shape::Ellipsoid { centre, radii } => Aabb {
                min: centre - radii,
                max: centre + radii,
            },
            Shape::Cylinder {
                base,
                radius,
                height,
            } => Aabb {
                min: base - v3(radius, radius, 0.0),
                max: base + v3(radius, radius, height),
            },
        }
    }

    /// Nearest intersection with `t` in (`t_min`, `t_max`).
    #[inline]
    pub fn intersect(&self, ray: &Ray, t_min: f32, t_max: f32) -> Option<ShapeHit> {
        match *self {
            Shape::Triangle { p0, e1, e2 } => {
                let p = ray.dir.cross(e2);
                let det = e1.dot(p);
                if det.abs() < 1e-12 {
                    return None;
                }
                let inv = 1.0 / det;
                let s = ray.origin - p0;
                let u = s.dot(p) * inv;
                if !(0.0..=1.0).contains(&u) {
                    return None;
                }
                let q = s.cross(e1);
                let v = ray.dir.dot(q) * inv;
                if v < 0.0 || u + v > 1.0 {
                    return None;
                }
                let t = e2.dot(q) * inv;
                (t > t_min && t < t_max).then(|| ShapeHit {
                    t,
                    t_exit: t,
                    normal: e1.cross(e2).normalized(),
                })
            }
            Shape::Ellipsoid { centre, radii } => {
                // Scale space so the ellipsoid is a unit sphere.
                let inv_r = v3(1.0 / radii.x, 1.0 / radii.y, 1.0 / radii.z);
                let o = (ray.origin - centre).mul_elem(inv_r);
                let d = ray.dir.mul_elem(inv_r);
                let a = d.dot(d);
                let b = o.dot(d);
                let c = o.dot(o) - 1.0;
                let disc = b * b - a * c;
                if disc < 0.0 {
                    return None;
                }
                let sq = disc.sqrt();
                let (t0, t1) = ((-b - sq) / a, (-b + sq) / a);
                let t = if t0 > t_min { t0 } else { t1 };
                if t <= t_min || t >= t_max {
                    return None;
                }
                let p = o + d * t;
                let normal = p.mul_elem(inv_r).normalized();
                Some(ShapeHit {
                    t,
                    t_exit: t1,
                    normal,
                })
            }
            Shape::Cylinder {
                base,
                radius,
                height,
            } => {
                let o = ray.origin - base;
                let d = ray.dir;
                let mut best: Option<ShapeHit> = None;
                let mut consider = |t: f32, normal: Vec3| {
                    if t > t_min && t < t_max && best.is_none_or(|b| t < b.t) {
                        best = Some(ShapeHit {
                            t,
                            t_exit: t,
                            normal,
                        });
                    }
                };
                let a = d.x * d.x + d.y * d.y;
                if a > 1e-12 {
                    let b = o.x * d.x + o.y * d.y;
                    let c = o.x * o.x + o.y * o.y - radius * radius;
                    let disc = b * b - a * c;
                    if disc >= 0.0 {
                        let sq = disc.sqrt();
                        for t in [(-b - sq) / a, (-b + sq) / a] {
                            let z = o.z + d.z * t;
                            if (0.0..=height).contains(&z) {
                                let p = o + d * t;
                                consider(t, v3(p.x, p.y, 0.0).normalized());
                            }
                        }
                    }
                }
                if d.z.abs() > 1e-12 {
                    for cap in [0.0, height] {
                        let t = (cap - o.z) / d.z;
                        let p = o + d * t;
                        if p.x * p.x + p.y * p.y <= radius * radius {
                            consider(t, v3(0.0, 0.0, 1.0));
                        }
                    }
                }
                best
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shapes_are_hit_at_the_right_distance() {
        let ray = Ray::new(v3(0.0, 0.0, 1.0), v3(1.0, 0.0, 0.0));
        let tri = Shape::triangle(v3(5.0, -1.0, 0.0), v3(5.0, 1.0, 0.0), v3(5.0, 0.0, 3.0));
        let h = tri.intersect(&ray, 0.0, 100.0).unwrap();
        assert!((h.t - 5.0).abs() < 1e-5 && h.normal.x.abs() > 0.99);
        assert!(tri.intersect(&ray, 0.0, 4.0).is_none());

        let ell = Shape::Ellipsoid {
            centre: v3(10.0, 0.0, 1.0),
            radii: v3(2.0, 1.0, 1.0),
        };
        let h = ell.intersect(&ray, 0.0, 100.0).unwrap();
        assert!((h.t - 8.0).abs() < 1e-4 && (h.t_exit - 12.0).abs() < 1e-4);
        assert!((h.normal.x + 1.0).abs() < 1e-4);

        let cyl = Shape::Cylinder {
            base: v3(3.0, 0.0, 0.0),
            radius: 0.5,
            height: 2.0,
        };
        let h = cyl.intersect(&ray, 0.0, 100.0).unwrap();
        assert!((h.t - 2.5).abs() < 1e-5);
        let above = Ray::new(v3(0.0, 0.0, 3.0), v3(1.0, 0.0, 0.0));
        assert!(cyl.intersect(&above, 0.0, 100.0).is_none());
        // Straight down onto the cap.
        let down = Ray::new(v3(3.0, 0.0, 5.0), v3(0.0, 0.0, -1.0));
        assert!((cyl.intersect(&down, 0.0, 100.0).unwrap().t - 3.0).abs() < 1e-5);

        let b = cyl.bounds();
        assert_eq!(b.hit(&ray, 100.0), Some(2.5));
        assert_eq!(b.hit(&above, 100.0), None);
    }
}
