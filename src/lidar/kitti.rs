//! KITTI / SemanticKITTI files on disk: `velodyne/*.bin` (float32 x, y, z,
//! reflectance) and `labels/*.label` (uint32, class in the low 16 bits). Its
//! error type is shared by the other dataset readers (nuScenes, PCD).

use std::path::Path;

use super::Scan;

/// Errors reading a dataset file (KITTI, nuScenes, PCD); each names the file.
#[derive(Debug, thiserror::Error)]
pub enum KittiError {
    #[error("{path}: {source}")]
    Io {
        path: String,
        source: std::io::Error,
    },
    #[error("{path}: {len} bytes is not a whole number of {record}-byte records")]
    Length {
        path: String,
        len: usize,
        record: usize,
    },
    #[error("{path}: {labels} labels for {points} points")]
    LabelCount {
        path: String,
        labels: usize,
        points: usize,
    },
    #[error("{path}: point {index}: {reason}")]
    Value {
        path: String,
        index: usize,
        reason: String,
    },
    #[error("{path}: {reason}")]
    Format { path: String, reason: String },
}

/// The dataset-reader error under a format-neutral name.
pub type DatasetError = KittiError;

fn read(path: &Path) -> Result<Vec<u8>, KittiError> {
    std::fs::read(path).map_err(|source| KittiError::Io {
        path: path.display().to_string(),
        source,
    })
}

/// Reads a KITTI `.bin` scan: float32 little-endian x, y, z, reflectance per point,
/// in the sensor's raw ring order.
pub fn read_bin(path: &Path) -> Result<Scan, KittiError> {
    let bytes = read(path)?;
    if bytes.len() % 16 != 0 {
        return Err(KittiError::Length {
            path: path.display().to_string(),
            len: bytes.len(),
            record: 16,
        });
    }
    let n = bytes.len() / 16;
    let mut xyz = Vec::with_capacity(n);
    let mut intensity = Vec::with_capacity(n);
    for rec in bytes.chunks_exact(16) {
        let f = |k: usize| {
            f32::from_le_bytes([rec[4 * k], rec[4 * k + 1], rec[4 * k + 2], rec[4 * k + 3]])
        };
        xyz.push([f(0), f(1), f(2)]);
        intensity.push(f(3));
    }
    let mut scan = Scan::from_xyz(xyz);
    scan.intensity = Some(intensity);
    Ok(scan)
}

/// Reads a SemanticKITTI `.label` file (uint32 per point; class in the low 16 bits,
/// instance in the high 16) and returns the full values.
pub fn read_labels(path: &Path) -> Result<Vec<u32>, KittiError> {
    let bytes = read(path)?;
    if bytes.len() % 4 != 0 {
        return Err(KittiError::Length {
            path: path.display().to_string(),
            len: bytes.len(),
            record: 4,
        });
    }
    Ok(bytes
        .chunks_exact(4)
        .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect())
}

/// Reads a scan and, when `labels` is given, attaches its labels (counts must match).
pub fn read_scan(bin: &Path, labels: Option<&Path>) -> Result<Scan, KittiError> {
    let mut scan = read_bin(bin)?;
    if let Some(path) = labels {
        let l = read_labels(path)?;
        if l.len() != scan.len() {
            return Err(KittiError::LabelCount {
                path: path.display().to_string(),
                labels: l.len(),
                points: scan.len(),
            });
        }
        scan.label = Some(l);
    }
    Ok(scan)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_points_and_rejects_ragged_files() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.bin");
        let mut bytes = Vec::new();
        for v in [1.0f32, 2.0, 3.0, 0.5, -4.0, 5.0, -6.0, 0.25] {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
        std::fs::write(&path, &bytes).unwrap();
        let scan = read_bin(&path).unwrap();
        assert_eq!(scan.xyz, vec![[1.0, 2.0, 3.0], [-4.0, 5.0, -6.0]]);
        assert_eq!(scan.intensity, Some(vec![0.5, 0.25]));

        std::fs::write(&path, &bytes[..30]).unwrap();
        let err = read_bin(&path).unwrap_err().to_string();
        assert!(err.contains("a.bin") && err.contains("30 bytes"), "{err}");

        let labels = dir.path().join("a.label");
        std::fs::write(&labels, 40u32.to_le_bytes()).unwrap();
        std::fs::write(&path, &bytes).unwrap();
        assert!(
            read_scan(&path, Some(&labels))
                .unwrap_err()
                .to_string()
                .contains("1 labels for 2 points")
        );
    }
}
