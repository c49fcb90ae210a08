//! The ego vehicle's drive through the street grid: a route of straight runs and
//! 90-degree turns at intersections, in the right-hand lane, at constant speed.
//! Gives the planar pose (x, y, yaw) and yaw rate at any time.

use crate::util::rng::Rng;

/// A planar pose in the world frame: position in meters, heading in radians
/// (counter-clockwise from +x).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlanarPose {
    pub x: f32,
    pub y: f32,
    pub yaw: f32,
}

/// A route through the grid as a dense polyline with cumulative arc length.
#[derive(Debug, Clone)]
pub struct Trajectory {
    points: Vec<[f32; 2]>,
    arc_m: Vec<f32>,
    pub speed_mps: f32,
    /// Grid street segments driven: (from node, to node) in grid coordinates.
    pub street_segments: Vec<([i32; 2], [i32; 2])>,
}

/// Unit direction of a grid heading 0..4 (east, north, west, south).
fn heading_dir(h: i32) -> [i32; 2] {
    match h.rem_euclid(4) {
        0 => [1, 0],
        1 => [0, 1],
        2 => [-1, 0],
        _ => [0, -1],
    }
}

impl Trajectory {
    /// A route on the grid with streets at `x = i * block_x`, `y = k * block_y`,
    /// starting mid-block on the street `y = 0` heading +x, long enough to drive
    /// `length_m`. At each intersection it goes straight, left or right by `rng`.
    pub fn on_grid(
        rng: &mut Rng,
        block_m: [f32; 2],
        lane_offset_m: f32,
        turn_radius_m: f32,
        length_m: f32,
        speed_mps: f32,
    ) -> Self {
        let mut node = [0i32, 0i32];
        let mut heading = 0i32;
        let node_pos = |n: [i32; 2]| [n[0] as f32 * block_m[0], n[1] as f32 * block_m[1]];
        // Lane point: offset to the right of travel.
        let lane = |p: [f32; 2], h: i32, along: f32| {
            let d = heading_dir(h);
            let right = [d[1] as f32, -(d[0] as f32)];
            [
                p[0] + right[0] * lane_offset_m + d[0] as f32 * along,
                p[1] + right[1] * lane_offset_m + d[1] as f32 * along,
            ]
        };
        let mut points = vec![lane(node_pos(node), heading, -0.5 * block_m[0])];
        let mut street_segments = Vec::new();
        let mut length = 0.0f32;
        let mut turned_last = false;
        while length < length_m + 20.0 {
            let d = heading_dir(heading);
            let next = [node[0] + d[0], node[1] + d[1]];
            street_segments.push((node, next));
            node = next;
            let draw = rng.uniform();
            // Never turn twice in a row, so the route does not circle one block.
            let turn = if turned_last || draw < 0.55 {
                0
            } else if draw < 0.775 {
                1
            } else {
                -1
            };
            let centre = node_pos(node);
            let prev = *points.last().unwrap_or(&centre);
            if turn == 0 {
                let p = lane(centre, heading, 0.0);
                length += (p[0] - prev[0]).hypot(p[1] - prev[1]);
                points.push(p);
                turned_last = false;
            } else {
                let out = heading + turn;
                // Corner of the two lane lines, then a quadratic Bezier fillet.
                let a = heading_dir(heading);
                let b = heading_dir(out);
                let li = lane(centre, heading, 0.0);
                let lo = lane(centre, out, 0.0);
                let corner = if a[0] != 0 {
                    [lo[0], li[1]]
                } else {
                    [li[0], lo[1]]
                };
                let r = turn_radius_m;
                let p0 = [corner[0] - a[0] as f32 * r, corner[1] - a[1] as f32 * r];
                let p2 = [corner[0] + b[0] as f32 * r, corner[1] + b[1] as f32 * r];
                let mut last = prev;
                for s in 0..=16 {
                    let u = s as f32 / 16.0;
                    let w = [(1.0 - u) * (1.0 - u), 2.0 * u * (1.0 - u), u * u];
                    let p = [
                        w[0] * p0[0] + w[1] * corner[0] + w[2] * p2[0],
                        w[0] * p0[1] + w[1] * corner[1] + w[2] * p2[1],
                    ];
                    length += (p[0] - last[0]).hypot(p[1] - last[1]);
                    points.push(p);
                    last = p;
                }
                heading = out;
                turned_last = true;
            }
        }
        let mut arc_m = Vec::with_capacity(points.len());
        let mut acc = 0.0;
        for (i, p) in points.iter().enumerate() {
            if i > 0 {
                acc += (p[0] - points[i - 1][0]).hypot(p[1] - points[i - 1][1]);
            }
            arc_m.push(acc);
        }
        Trajectory {
            points,
            arc_m,
            speed_mps,
            street_segments,
        }
    }

    pub fn length_m(&self) -> f32 {
        self.arc_m.last().copied().unwrap_or(0.0)
    }

    /// The polyline vertices (for scene layout and plots).
    pub fn points(&self) -> &[[f32; 2]] {
        &self.points
    }

    fn position_at_arc(&self, s: f32) -> [f32; 2] {
        let s = s.clamp(0.0, self.length_m());
        let i = self
            .arc_m
            .partition_point(|&a| a <= s)
            .clamp(1, self.points.len().max(2) - 1);
        let (a, b) = (self.points[i - 1], self.points[i]);
        let seg = self.arc_m[i] - self.arc_m[i - 1];
        let u = if seg > 0.0 {
            (s - self.arc_m[i - 1]) / seg
        } else {
            0.0
        };
        [a[0] + (b[0] - a[0]) * u, a[1] + (b[1] - a[1]) * u]
    }

    /// Pose at arc length `s`; heading from a centred difference over 1 m.
    pub fn pose_at_arc(&self, s: f32) -> PlanarPose {
        let p = self.position_at_arc(s);
        let a = self.position_at_arc(s - 0.5);
        let b = self.position_at_arc(s + 0.5);
        PlanarPose {
            x: p[0],
            y: p[1],
            yaw: (b[1] - a[1]).atan2(b[0] - a[0]),
        }
    }

    /// Pose at time `t_s` after the start of the drive.
    pub fn pose_at(&self, t_s: f32) -> PlanarPose {
        self.pose_at_arc(t_s * self.speed_mps)
    }

    /// Yaw rate (rad/s) at time `t_s`.
    pub fn yaw_rate_at(&self, t_s: f32) -> f32 {
        let dt = 0.05;
        let a = self.pose_at(t_s - dt).yaw;
        let b = self.pose_at(t_s + dt).yaw;
        super::wrap_angle(b - a) / (2.0 * dt)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn route_is_continuous_and_moves_at_speed() {
        for seed in 0..5 {
            let mut rng = Rng::keyed(seed, 9);
            let traj = Trajectory::on_grid(&mut rng, [90.0, 70.0], 1.7, 8.0, 400.0, 10.0);
            assert!(traj.length_m() >= 400.0);
            let mut prev = traj.pose_at(0.0);
            for k in 1..400 {
                let p = traj.pose_at(k as f32 * 0.1);
                let step = (p.x - prev.x).hypot(p.y - prev.y);
                assert!(
                    (step - 1.0).abs() < 0.05,
                    "seed {seed} scan {k}: step {step}"
                );
                prev = p;
            }
        }
        // Heading +x at the start, in the right (y < 0) lane.
        let traj = Trajectory::on_grid(&mut Rng::keyed(0, 9), [90.0, 70.0], 1.7, 8.0, 100.0, 10.0);
        let p = traj.pose_at(0.0);
        assert!(p.yaw.abs() < 1e-3 && (p.y + 1.7).abs() < 1e-3);
    }
}
