//! Procedural street scenes from a seed: a grid of streets (cambered roads, curbs,
//! raised sidewalks, a global slope), blocks with building rows at varying setbacks
//! and angles (glass window bands), walls, fences, hedges, trees, bushes, poles,
//! traffic signs, parked cars, and moving actors (cars, pedestrians, cyclists),
//! plus the ego route through it. Static geometry goes into one BVH built once;
//! moving actors are instanced into a small BVH per scan time.

use super::bvh::Bvh;
use super::geometry::{Primitive, Ray, Shape, Vec3, v3};
use super::material::{SURFACES, Surface};
use super::trajectory::{PlanarPose, Trajectory};
use crate::util::rng::{Rng, key_hash, unit_f32};

use super::builder::{Actor, Builder, car_template, cyclist_template};
pub use super::street::Layout;
use super::street::{block, intersection, road_strip};

/// What to generate: the seed, and the drive the scene must cover.
#[derive(Debug, Clone, PartialEq)]
pub struct SceneConfig {
    pub seed: u64,
    /// Ego speed along the route, m/s.
    pub speed_mps: f32,
    /// Length of the drive in seconds (sets the route length).
    pub duration_s: f32,
    /// Objects are generated out to this distance (plus a margin) from the route.
    pub max_range_m: f32,
    /// Height of the sensor's origin above the road (KITTI: 1.73 m).
    pub sensor_height_m: f32,
}

impl Default for SceneConfig {
    fn default() -> Self {
        SceneConfig {
            seed: 0,
            speed_mps: 10.0,
            duration_s: 10.0,
            max_range_m: 80.0,
            sensor_height_m: 1.73,
        }
    }
}

/// A first hit of a ray in the scene.
#[derive(Debug, Clone, Copy)]
pub struct SceneHit {
    pub t: f32,
    /// Unit surface normal, facing the ray's origin.
    pub normal: Vec3,
    pub surface: Surface,
    pub instance: u16,
}

/// A generated scene: layout, ego route, static BVH and moving actors.
#[derive(Debug, Clone)]
pub struct Scene {
    pub config: SceneConfig,
    pub layout: Layout,
    pub trajectory: Trajectory,
    static_bvh: Bvh,
    actors: Vec<Actor>,
}

impl Scene {
    /// The scene of `config.seed`. One function on purpose: every random draw comes from one
    /// sequence in the order read here (layout, streets, blocks, actors, route), and that
    /// order is what makes a seed's scene the same on every version that keeps it.
    pub fn generate(config: SceneConfig) -> Scene {
        let seed = config.seed;
        let mut rng = Rng::keyed(seed, 1);
        let road_half_width_m = rng.range(3.6, 6.2);
        let layout = Layout {
            block_m: [rng.range(70.0, 130.0), rng.range(60.0, 110.0)],
            road_half_width_m,
            sidewalk_m: rng.range(2.0, 4.0),
            curb_m: rng.range(0.1, 0.18),
            camber: rng.range(0.01, 0.025),
            slope: [rng.range(-0.03, 0.03), rng.range(-0.03, 0.03)],
            lane_offset_m: 1.7,
            parking: road_half_width_m >= 5.0,
        };
        let length = config.speed_mps.max(0.0) * config.duration_s.max(0.0);
        let trajectory = Trajectory::on_grid(
            &mut Rng::keyed(seed, 2),
            layout.block_m,
            layout.lane_offset_m,
            8.0,
            length,
            config.speed_mps,
        );
        let margin = config.max_range_m + 25.0;
        let route: Vec<[f32; 2]> = sample_route(&trajectory, 4.0);
        let near = |x0: f32, y0: f32, x1: f32, y1: f32| {
            route.iter().any(|p| {
                let dx = (x0 - p[0]).max(p[0] - x1).max(0.0);
                let dy = (y0 - p[1]).max(p[1] - y1).max(0.0);
                dx * dx + dy * dy <= margin * margin
            })
        };
        let (mut lo, mut hi) = ([f32::INFINITY; 2], [f32::NEG_INFINITY; 2]);
        for p in &route {
            for a in 0..2 {
                lo[a] = lo[a].min(p[a] - margin);
                hi[a] = hi[a].max(p[a] + margin);
            }
        }
        let [bx, by] = layout.block_m;
        let (i0, i1) = ((lo[0] / bx).floor() as i32, (hi[0] / bx).ceil() as i32);
        let (k0, k1) = ((lo[1] / by).floor() as i32, (hi[1] / by).ceil() as i32);
        let hw = layout.road_half_width_m;
        let mut b = Builder::new(layout.slope);
        let mut srng = Rng::keyed(seed, 3);
        let mut actors = Vec::new();

        // Roads: street segments between intersections, and the intersections.
        let crown = layout.camber * hw;
        for i in i0..=i1 {
            for k in k0..=k1 {
                let (x, y) = (i as f32 * bx, k as f32 * by);
                if near(x - hw, y - hw, x + hw, y + hw) {
                    intersection(&mut b, x, y, hw, crown);
                }
                // Street along x from this node to the next, and along y.
                if i < i1 && near(x + hw, y - hw, x + bx - hw, y + hw) {
                    road_strip(&mut b, [x + hw, y], [1.0, 0.0], bx - 2.0 * hw, hw, crown);
                }
                if k < k1 && near(x - hw, y + hw, x + hw, y + by - hw) {
                    road_strip(&mut b, [x, y + hw], [0.0, 1.0], by - 2.0 * hw, hw, crown);
                }
            }
        }
        // Blocks.
        for i in i0..i1 {
            for k in k0..k1 {
                let (x0, y0) = (i as f32 * bx + hw, k as f32 * by + hw);
                let (x1, y1) = ((i + 1) as f32 * bx - hw, (k + 1) as f32 * by - hw);
                if !near(x0, y0, x1, y1) {
                    continue;
                }
                block(&mut b, &mut srng, &layout, [x0, y0, x1, y1], &mut actors);
            }
        }
        // Moving cars and cyclists along whole street lines, never in the ego's
        // own lane direction on a street it drives.
        let ego_uses = |horizontal: bool, line: i32, positive: bool| {
            trajectory.street_segments.iter().any(|(a, c)| {
                if horizontal {
                    a[1] == c[1] && a[1] == line && ((c[0] > a[0]) == positive)
                } else {
                    a[0] == c[0] && a[0] == line && ((c[1] > a[1]) == positive)
                }
            })
        };
        let mut lines = Vec::new();
        for k in k0..=k1 {
            lines.push((
                true,
                k,
                [i0 as f32 * bx, k as f32 * by],
                (i1 - i0) as f32 * bx,
            ));
        }
        for i in i0..=i1 {
            lines.push((
                false,
                i,
                [i as f32 * bx, k0 as f32 * by],
                (k1 - k0) as f32 * by,
            ));
        }
        for (horizontal, line, start, span) in lines {
            for positive in [true, false] {
                let along = match (horizontal, positive) {
                    (true, true) => [1.0, 0.0],
                    (true, false) => [-1.0, 0.0],
                    (false, true) => [0.0, 1.0],
                    (false, false) => [0.0, -1.0],
                };
                let right = [along[1], -along[0]];
                let origin = if positive {
                    start
                } else {
                    [start[0] + along[0] * -span, start[1] + along[1] * -span]
                };
                let in_lane =
                    |offset: f32| [origin[0] + right[0] * offset, origin[1] + right[1] * offset];
                if !ego_uses(horizontal, line, positive) {
                    let cars = (span / 120.0 * srng.range(0.0, 2.0)).round() as usize;
                    for _ in 0..cars {
                        let mut tb = Builder::new([0.0; 2]);
                        let inst = b.instance();
                        car_template(&mut srng, &mut tb, inst);
                        actors.push(Actor {
                            template: tb.prims,
                            start: in_lane(layout.lane_offset_m),
                            dir: along,
                            speed_mps: srng.range(5.0, 14.0),
                            phase_m: srng.range(0.0, span),
                            span_m: span,
                        });
                    }
                }
                if !ego_uses(horizontal, line, positive) && srng.chance(0.35) {
                    let offset = if layout.parking { hw - 2.6 } else { hw - 0.8 };
                    let mut tb = Builder::new([0.0; 2]);
                    let inst = b.instance();
                    cyclist_template(&mut srng, &mut tb, inst);
                    actors.push(Actor {
                        template: tb.prims,
                        start: in_lane(offset),
                        dir: along,
                        speed_mps: srng.range(3.0, 6.0),
                        phase_m: srng.range(0.0, span),
                        span_m: span,
                    });
                }
            }
        }
        let static_bvh = Bvh::build(b.prims);
        Scene {
            config,
            layout,
            trajectory,
            static_bvh,
            actors,
        }
    }

    /// Number of static primitives (for reports).
    pub fn static_primitives(&self) -> usize {
        self.static_bvh.prims.len()
    }

    pub fn actor_count(&self) -> usize {
        self.actors.len()
    }

    /// The moving actors placed at time `t_s`, within `radius_m` of `centre`.
    pub fn dynamic_bvh(&self, t_s: f32, centre: [f32; 2], radius_m: f32) -> Bvh {
        let mut prims = Vec::new();
        for actor in &self.actors {
            let p = actor.position(t_s);
            if (p[0] - centre[0]).hypot(p[1] - centre[1]) > radius_m + 5.0 {
                continue;
            }
            let (s, c) = actor.dir[1].atan2(actor.dir[0]).sin_cos();
            let z = self.layout.ground_z(p[0], p[1]);
            let place = |q: Vec3| v3(p[0] + c * q.x - s * q.y, p[1] + s * q.x + c * q.y, q.z + z);
            for prim in &actor.template {
                let shape = match prim.shape {
                    Shape::Triangle { p0, e1, e2 } => {
                        Shape::triangle(place(p0), place(p0 + e1), place(p0 + e2))
                    }
                    Shape::Ellipsoid { centre, radii } => Shape::Ellipsoid {
                        centre: place(centre),
                        radii,
                    },
                    Shape::Cylinder {
                        base,
                        radius,
                        height,
                    } => Shape::Cylinder {
                        base: place(base),
                        radius,
                        height,
                    },
                };
                prims.push(Primitive { shape, ..*prim });
            }
        }
        Bvh::build(prims)
    }

    /// First hit along `ray` (unit direction) closer than `t_max`, in the static
    /// scene and in `dynamic`. `ray_key` seeds the free path inside porous media.
    pub fn cast(&self, dynamic: &Bvh, ray: &Ray, t_max: f32, ray_key: u64) -> Option<SceneHit> {
        let mut best = self
            .static_bvh
            .nearest(ray, 1e-4, t_max, |p, h| {
                accept_hit(&self.static_bvh, ray_key, 0, p, h)
            })
            .map(|h| (h, &self.static_bvh));
        let limit = best.map_or(t_max, |(h, _)| h.hit.t);
        if let Some(h) = dynamic.nearest(ray, 1e-4, limit, |p, h| {
            accept_hit(dynamic, ray_key, 1, p, h)
        }) {
            best = Some((h, dynamic));
        }
        best.map(|(h, bvh)| {
            let prim = &bvh.prims[h.prim as usize];
            let n = h.hit.normal;
            let normal = if n.dot(ray.dir) > 0.0 { -n } else { n };
            SceneHit {
                t: h.hit.t,
                normal,
                surface: SURFACES[prim.surface as usize],
                instance: prim.instance,
            }
        })
    }

    /// Ego pose at time `t_s`, with the ground height under it.
    pub fn ego_pose(&self, t_s: f32) -> (PlanarPose, f32) {
        let p = self.trajectory.pose_at(t_s);
        let crown =
            self.layout.camber * (self.layout.road_half_width_m - self.layout.lane_offset_m);
        (p, self.layout.ground_z(p.x, p.y) + crown)
    }
}

/// Distance at which a ray really stops on primitive `prim`: the surface for solid
/// shapes; inside porous media (tree crowns) after an exponential free path keyed
/// by the ray, or nowhere (None) if that lies beyond the exit.
fn accept_hit(
    bvh: &Bvh,
    ray_key: u64,
    salt: u64,
    prim: u32,
    hit: &super::geometry::ShapeHit,
) -> Option<f32> {
    let surface = &SURFACES[bvh.prims[prim as usize].surface as usize];
    if surface.mean_free_path_m <= 0.0 {
        return Some(hit.t);
    }
    let u = unit_f32(key_hash(&[ray_key, salt, prim as u64])).max(1e-7);
    let t = hit.t - surface.mean_free_path_m * u.ln();
    (t < hit.t_exit).then_some(t)
}

fn sample_route(traj: &Trajectory, step: f32) -> Vec<[f32; 2]> {
    let n = (traj.length_m() / step).ceil() as usize + 1;
    (0..=n)
        .map(|k| {
            let p = traj.pose_at_arc(k as f32 * step);
            [p.x, p.y]
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scenes_are_reproducible_and_vary_with_the_seed() {
        let cfg = |seed| SceneConfig {
            seed,
            duration_s: 3.0,
            ..Default::default()
        };
        let a = Scene::generate(cfg(5));
        let b = Scene::generate(cfg(5));
        let c = Scene::generate(cfg(6));
        assert_eq!(a.static_primitives(), b.static_primitives());
        assert_eq!(a.layout, b.layout);
        assert_ne!(a.layout, c.layout);
        assert!(a.static_primitives() > 1000, "{}", a.static_primitives());
        assert!(a.actor_count() > 0);
    }

    #[test]
    fn ground_below_the_ego_is_road_at_sensor_height() {
        let scene = Scene::generate(SceneConfig {
            seed: 3,
            duration_s: 2.0,
            ..Default::default()
        });
        let (pose, z) = scene.ego_pose(0.0);
        let dynamic = scene.dynamic_bvh(0.0, [pose.x, pose.y], 80.0);
        let origin = v3(pose.x + 4.0, pose.y, z + 1.73);
        let hit = scene
            .cast(&dynamic, &Ray::new(origin, v3(0.0, 0.0, -1.0)), 100.0, 0)
            .unwrap();
        assert_eq!(hit.surface.label, super::super::material::label::ROAD);
        assert!((hit.t - 1.73).abs() < 0.1, "{}", hit.t);
        assert!(hit.normal.z > 0.99);
    }
}
