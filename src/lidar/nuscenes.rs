//! nuScenes `LIDAR_TOP` files on disk (`*.pcd.bin`): float32 little-endian
//! x, y, z, intensity, ring per point, in column-major firing order (the ring index
//! cycles fastest), 32 rings of a Velodyne HDL-32E.

use std::path::Path;

use super::Scan;
use super::kitti::KittiError;

/// Bytes per nuScenes point: five float32.
const RECORD: usize = 20;

/// Reads a nuScenes `.pcd.bin` scan. The ring field is kept (nuScenes numbers rings
/// bottom-up: ring 0 is the lowest beam); the cloud is unorganized (`height == 1`),
/// so [`super::Strategy::Auto`] projects it by ring field.
pub fn read_bin(path: &Path) -> Result<Scan, KittiError> {
    let name = || path.display().to_string();
    let bytes = std::fs::read(path).map_err(|source| KittiError::Io {
        path: name(),
        source,
    })?;
    if bytes.len() % RECORD != 0 {
        return Err(KittiError::Length {
            path: name(),
            len: bytes.len(),
            record: RECORD,
        });
    }
    let n = bytes.len() / RECORD;
    let (mut xyz, mut intensity, mut ring) = (
        Vec::with_capacity(n),
        Vec::with_capacity(n),
        Vec::with_capacity(n),
    );
    for (i, rec) in bytes.chunks_exact(RECORD).enumerate() {
        let f = |k: usize| {
            f32::from_le_bytes([rec[4 * k], rec[4 * k + 1], rec[4 * k + 2], rec[4 * k + 3]])
        };
        let r = f(4);
        if !(r.is_finite() && r >= 0.0 && r <= f32::from(u16::MAX) && r.fract() == 0.0) {
            return Err(KittiError::Value {
                path: name(),
                index: i,
                reason: format!("ring {r} is not a small whole number"),
            });
        }
        xyz.push([f(0), f(1), f(2)]);
        intensity.push(f(3));
        ring.push(r as u16);
    }
    let mut scan = Scan::from_xyz(xyz);
    scan.intensity = Some(intensity);
    scan.ring = Some(ring);
    Ok(scan)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write(path: &Path, values: &[f32]) {
        let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        std::fs::write(path, bytes).unwrap();
    }

    #[test]
    fn reads_points_and_rings_and_rejects_bad_files() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.pcd.bin");
        write(
            &path,
            &[1.0, 2.0, 3.0, 40.0, 0.0, -1.0, 0.5, -2.0, 7.0, 31.0],
        );
        let scan = read_bin(&path).unwrap();
        assert_eq!(scan.xyz, vec![[1.0, 2.0, 3.0], [-1.0, 0.5, -2.0]]);
        assert_eq!(scan.intensity, Some(vec![40.0, 7.0]));
        assert_eq!(scan.ring, Some(vec![0, 31]));

        write(&path, &[1.0, 2.0, 3.0, 40.0]);
        assert!(
            read_bin(&path)
                .unwrap_err()
                .to_string()
                .contains("16 bytes is not a whole number of 20-byte records")
        );
        write(&path, &[1.0, 2.0, 3.0, 40.0, 2.5]);
        let err = read_bin(&path).unwrap_err().to_string();
        assert!(err.contains("point 0") && err.contains("ring 2.5"), "{err}");
    }
}
