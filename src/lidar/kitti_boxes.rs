//! Point labels from KITTI object annotations: `label_2/*.txt` (3D boxes in the rectified
//! camera frame) and `calib/*.txt` (the LiDAR-to-camera transform and the image
//! projection). Boxes only cover what the front camera sees, so they give partial labels:
//! points in a car or pedestrian box are car or person, points in the camera's view outside
//! every box are [`IN_VIEW_NO_BOX`] (any class but those two), and everything else (behind
//! the camera, in a box of another kind or a `DontCare` region, or at a box's edge) stays
//! unlabelled.

use std::path::Path;

use nalgebra::{Matrix3, Matrix3x4, Vector3, Vector4};

use super::kitti::KittiError;

/// SemanticKITTI ids the boxes map onto.
const CAR_ID: u32 = 10;
const PERSON_ID: u32 = 30;
const BICYCLIST_ID: u32 = 31;
/// Unlabelled (SemanticKITTI's 0).
const UNLABELLED_ID: u32 = 0;

/// A label id of this tool's own, outside SemanticKITTI's range: the point is in the
/// annotated camera view and in no box, so it is neither a car nor a person.
pub const IN_VIEW_NO_BOX: u32 = 0xF000;

/// Image area every KITTI object frame covers (frames are 1224-1242 x 370-375 pixels).
const IMAGE_WIDTH: f64 = 1224.0;
const IMAGE_HEIGHT: f64 = 370.0;

/// Points this close to a box's faces (outside or in) are left unlabelled: box annotations
/// are loose by a few centimetres, and the ground under a car sits on its box's floor.
const EDGE_M: f64 = 0.2;

/// The transforms of one KITTI object frame.
#[derive(Debug, Clone, PartialEq)]
pub struct Calib {
    /// Rectified camera 2's projection (`P2`).
    pub p2: Matrix3x4<f64>,
    /// Rectifying rotation (`R0_rect`).
    pub r0: Matrix3<f64>,
    /// LiDAR to (unrectified) camera (`Tr_velo_to_cam`).
    pub velo_to_cam: Matrix3x4<f64>,
}

impl Calib {
    /// A LiDAR point in the rectified camera frame (x right, y down, z forward).
    pub fn to_camera(&self, p: [f32; 3]) -> Vector3<f64> {
        let v = Vector4::new(p[0] as f64, p[1] as f64, p[2] as f64, 1.0);
        self.r0 * (self.velo_to_cam * v)
    }

    /// Where a point in the rectified camera frame lands in the image (pixels), if it is in
    /// front of the camera and inside the image.
    pub fn image_position(&self, c: &Vector3<f64>) -> Option<(f64, f64)> {
        if c.z <= 0.1 {
            return None;
        }
        let uvw = self.p2 * Vector4::new(c.x, c.y, c.z, 1.0);
        let (u, v) = (uvw.x / uvw.z, uvw.y / uvw.z);
        ((0.0..IMAGE_WIDTH).contains(&u) && (0.0..IMAGE_HEIGHT).contains(&v)).then_some((u, v))
    }
}

/// One line of a `label_2` file.
#[derive(Debug, Clone, PartialEq)]
pub struct Object {
    /// `Car`, `Pedestrian`, `DontCare`, ...
    pub kind: String,
    /// 2D box in the image: left, top, right, bottom (pixels).
    pub bbox: [f64; 4],
    /// Height, width, length (metres).
    pub size: [f64; 3],
    /// Centre of the box's floor in the rectified camera frame.
    pub bottom: Vector3<f64>,
    /// Rotation about the camera's y axis.
    pub ry: f64,
}

impl Object {
    /// The SemanticKITTI id of the points in this box; `None` for kinds the benchmark's
    /// classes do not pin down (van, truck, tram, misc, DontCare), whose points stay
    /// unlabelled.
    fn label_id(&self) -> Option<u32> {
        match self.kind.as_str() {
            "Car" => Some(CAR_ID),
            "Pedestrian" | "Person_sitting" => Some(PERSON_ID),
            "Cyclist" => Some(BICYCLIST_ID),
            _ => None,
        }
    }

    /// Signed distance outside the box (negative inside), along the box's own axes: the
    /// largest excess over a face.
    fn outside_m(&self, c: &Vector3<f64>) -> f64 {
        let d = c - self.bottom;
        let (s, co) = self.ry.sin_cos();
        // The box's corners are R(ry) * local + bottom; local = R(ry)^T * d.
        let along = co * d.x - s * d.z;
        let across = s * d.x + co * d.z;
        let [h, w, l] = self.size;
        let up = -d.y; // camera y points down
        [
            along.abs() - l / 2.0,
            across.abs() - w / 2.0,
            up - h,
            -up, // below the floor
        ]
        .into_iter()
        .fold(f64::MIN, f64::max)
    }

    /// How deep inside a box a point must be to take its class: a car's box is loose by
    /// a few centimetres; a pedestrian's is hardly wider than the person.
    fn inner_margin_m(&self) -> f64 {
        if self.kind == "Car" { EDGE_M } else { 0.0 }
    }

    /// Height of a point above the box's floor (the ground under the object lies there).
    fn height_above_floor(&self, c: &Vector3<f64>) -> f64 {
        self.bottom.y - c.y
    }

    fn has_3d_box(&self) -> bool {
        self.size.iter().all(|&s| s > 0.0)
    }
}

fn format_error(path: &Path, reason: String) -> KittiError {
    KittiError::Format {
        path: path.display().to_string(),
        reason,
    }
}

fn read_text(path: &Path) -> Result<String, KittiError> {
    std::fs::read_to_string(path).map_err(|source| KittiError::Io {
        path: path.display().to_string(),
        source,
    })
}

/// Reads a KITTI object `calib` file.
pub fn read_calib(path: &Path) -> Result<Calib, KittiError> {
    let text = read_text(path)?;
    let values = |key: &str, n: usize| -> Result<Vec<f64>, KittiError> {
        let line = text
            .lines()
            .find_map(|l| l.strip_prefix(key).and_then(|r| r.strip_prefix(':')))
            .ok_or_else(|| format_error(path, format!("no {key} line")))?;
        let v: Vec<f64> = line
            .split_whitespace()
            .map(str::parse)
            .collect::<Result<_, _>>()
            .map_err(|e| format_error(path, format!("{key}: {e}")))?;
        if v.len() != n || v.iter().any(|x| !x.is_finite()) {
            return Err(format_error(
                path,
                format!("{key}: expected {n} finite numbers, got {}", v.len()),
            ));
        }
        Ok(v)
    };
    Ok(Calib {
        p2: Matrix3x4::from_row_slice(&values("P2", 12)?),
        r0: Matrix3::from_row_slice(&values("R0_rect", 9)?),
        velo_to_cam: Matrix3x4::from_row_slice(&values("Tr_velo_to_cam", 12)?),
    })
}

/// Reads a KITTI object `label_2` file (one object per line, 15 fields).
pub fn read_objects(path: &Path) -> Result<Vec<Object>, KittiError> {
    let text = read_text(path)?;
    let mut objects = Vec::new();
    for (i, line) in text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty())
    {
        let fields: Vec<&str> = line.split_whitespace().collect();
        let bad = |reason: String| format_error(path, format!("line {}: {reason}", i + 1));
        if fields.len() < 15 {
            return Err(bad(format!("{} fields, expected 15", fields.len())));
        }
        let v: Vec<f64> = fields[1..15]
            .iter()
            .map(|f| f.parse::<f64>())
            .collect::<Result<_, _>>()
            .map_err(|e| bad(e.to_string()))?;
        if v.iter().any(|x| !x.is_finite()) {
            return Err(bad("a number is not finite".into()));
        }
        objects.push(Object {
            kind: fields[0].to_string(),
            bbox: [v[3], v[4], v[5], v[6]],
            size: [v[7], v[8], v[9]],
            bottom: Vector3::new(v[10], v[11], v[12]),
            ry: v[13],
        });
    }
    Ok(objects)
}

/// A SemanticKITTI-style label per point (see the module doc).
pub fn point_labels(xyz: &[[f32; 3]], calib: &Calib, objects: &[Object]) -> Vec<u32> {
    xyz.iter()
        .map(|&p| {
            let c = calib.to_camera(p);
            let Some((u, v)) = calib.image_position(&c) else {
                return UNLABELLED_ID;
            };
            let mut label = IN_VIEW_NO_BOX;
            for o in objects {
                if !o.has_3d_box() {
                    let [l, t, r, b] = o.bbox;
                    if (l..=r).contains(&u) && (t..=b).contains(&v) {
                        label = UNLABELLED_ID; // DontCare: an unannotated object may be here
                    }
                    continue;
                }
                let out = o.outside_m(&c);
                if out > EDGE_M {
                    continue;
                }
                match o.label_id() {
                    Some(id) if out <= -o.inner_margin_m() && o.height_above_floor(&c) > EDGE_M => {
                        return id;
                    }
                    _ => label = UNLABELLED_ID,
                }
            }
            label
        })
        .collect()
}

/// Reads a scan's boxes and calibration and labels its points.
pub fn read_point_labels(
    xyz: &[[f32; 3]],
    label_2: &Path,
    calib: &Path,
) -> Result<Vec<u32>, KittiError> {
    Ok(point_labels(
        xyz,
        &read_calib(calib)?,
        &read_objects(label_2)?,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The LiDAR frame (x forward, y left, z up) turned into the camera frame (x right, y
    /// down, z forward), no offset.
    fn calib() -> Calib {
        let velo_to_cam = Matrix3x4::new(
            0.0, -1.0, 0.0, 0.0, //
            0.0, 0.0, -1.0, 0.0, //
            1.0, 0.0, 0.0, 0.0,
        );
        let p2 = Matrix3x4::new(
            700.0, 0.0, 612.0, 0.0, //
            0.0, 700.0, 185.0, 0.0, //
            0.0, 0.0, 1.0, 0.0,
        );
        Calib {
            p2,
            r0: Matrix3::identity(),
            velo_to_cam,
        }
    }

    /// A car 10 m ahead (camera z), its floor 1.7 m below the camera, 4 m long along z.
    fn car() -> Object {
        Object {
            kind: "Car".into(),
            bbox: [500.0, 150.0, 700.0, 260.0],
            size: [1.5, 1.6, 4.0],
            bottom: Vector3::new(0.0, 1.7, 10.0),
            ry: std::f64::consts::FRAC_PI_2, // length along the camera's z axis
        }
    }

    #[test]
    fn points_in_a_box_take_its_class_and_the_rest_of_the_view_is_neither_car_nor_person() {
        let objects = [car()];
        // LiDAR frame: x forward, z up. The car's middle: 10 m ahead, 1.7 - 0.75 m below.
        let points = [
            [10.0, 0.0, -0.95], // inside the car
            [11.9, 0.0, -0.95], // 0.1 m inside its far face: at the edge
            [20.0, 0.0, -0.95], // in view, no box
            [-10.0, 0.0, 0.0],  // behind the camera
            [10.0, 0.0, -1.75], // ground just under the car's floor: at the edge
        ];
        let labels = point_labels(&points, &calib(), &objects);
        assert_eq!(
            labels,
            [
                CAR_ID,
                UNLABELLED_ID,
                IN_VIEW_NO_BOX,
                UNLABELLED_ID,
                UNLABELLED_ID
            ]
        );
    }

    #[test]
    fn other_kinds_and_dont_care_regions_stay_unlabelled() {
        let van = Object {
            kind: "Van".into(),
            ..car()
        };
        let dont_care = Object {
            kind: "DontCare".into(),
            bbox: [0.0, 0.0, 1224.0, 370.0],
            size: [-1.0, -1.0, -1.0],
            bottom: Vector3::new(-1000.0, -1000.0, -1000.0),
            ry: -10.0,
        };
        let points = [[10.0, 0.0, -0.95], [20.0, 0.0, -0.95]];
        assert_eq!(
            point_labels(&points, &calib(), &[van]),
            [UNLABELLED_ID, IN_VIEW_NO_BOX]
        );
        assert_eq!(
            point_labels(&points, &calib(), &[dont_care]),
            [UNLABELLED_ID, UNLABELLED_ID]
        );
    }

    #[test]
    fn reads_kitti_files_and_names_the_file_on_a_bad_line() {
        let dir = tempfile::tempdir().unwrap();
        let calib_path = dir.path().join("000001.txt");
        let row = |v: &[f64]| {
            v.iter()
                .map(|x| format!("{x:e}"))
                .collect::<Vec<_>>()
                .join(" ")
        };
        std::fs::write(
            &calib_path,
            format!(
                "P0: {}\nP2: {}\nR0_rect: {}\nTr_velo_to_cam: {}\n",
                row(&[0.0; 12]),
                row(&[
                    700.0, 0.0, 612.0, 0.0, 0.0, 700.0, 185.0, 0.0, 0.0, 0.0, 1.0, 0.0
                ]),
                row(&[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]),
                row(&[0.0, -1.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0]),
            ),
        )
        .unwrap();
        assert_eq!(read_calib(&calib_path).unwrap(), calib());
        let label_path = dir.path().join("label.txt");
        std::fs::write(
            &label_path,
            "Car 0.00 0 -1.55 500 150 700 260 1.5 1.6 4.0 0.0 1.7 10.0 1.5707963267948966\n",
        )
        .unwrap();
        let objects = read_objects(&label_path).unwrap();
        assert_eq!(objects.len(), 1);
        assert_eq!(objects[0].kind, "Car");
        assert!((objects[0].ry - car().ry).abs() < 1e-12);
        std::fs::write(&label_path, "Car 0.00 0 -1.55 500 150\n").unwrap();
        let err = read_objects(&label_path).unwrap_err().to_string();
        assert!(err.contains("label.txt") && err.contains("line 1"), "{err}");
    }
}
