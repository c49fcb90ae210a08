//! PCL `.pcd` files on disk (format v0.7), `DATA ascii` and `DATA binary`:
//! x, y, z (float32 or float64), optional intensity, ring (`ring` / `channel` /
//! `laser_id`) and label fields of any numeric type. `binary_compressed` (LZF) is
//! refused with a clear error rather than half supported.

use std::path::Path;

use super::Scan;
use super::kitti::DatasetError;
use super::scan::ring_ids;

/// One PCD field: its name, byte size and type letter (`F`, `U`, `I`). Fields
/// with COUNT > 1 are read at their first value.
#[derive(Debug, Clone)]
struct Field {
    name: String,
    size: usize,
    kind: u8,
    /// Byte offset inside a binary record.
    offset: usize,
    /// Index of the first value inside an ASCII line.
    column: usize,
}

impl Field {
    /// The value at `bytes` (exactly `size` long), as f64.
    fn decode(&self, b: &[u8]) -> Option<f64> {
        Some(match (self.kind, self.size) {
            (b'F', 4) => f64::from(f32::from_le_bytes(b.try_into().ok()?)),
            (b'F', 8) => f64::from_le_bytes(b.try_into().ok()?),
            (b'U', 1) => f64::from(b[0]),
            (b'U', 2) => f64::from(u16::from_le_bytes(b.try_into().ok()?)),
            (b'U', 4) => f64::from(u32::from_le_bytes(b.try_into().ok()?)),
            (b'U', 8) => u64::from_le_bytes(b.try_into().ok()?) as f64,
            (b'I', 1) => f64::from(b[0] as i8),
            (b'I', 2) => f64::from(i16::from_le_bytes(b.try_into().ok()?)),
            (b'I', 4) => f64::from(i32::from_le_bytes(b.try_into().ok()?)),
            (b'I', 8) => i64::from_le_bytes(b.try_into().ok()?) as f64,
            _ => return None,
        })
    }
}

/// Reads a `.pcd` file into a [`Scan`] (organized when `HEIGHT > 1`).
pub fn read_pcd(path: &Path) -> Result<Scan, DatasetError> {
    read_pcd_noted(path).map(|(scan, _)| scan)
}

/// [`read_pcd`], with what a user should know about a file that is read anyway: data past
/// `POINTS`, a ring field that could not be used.
pub fn read_pcd_noted(path: &Path) -> Result<(Scan, Vec<String>), DatasetError> {
    let name = path.display().to_string();
    let bytes = std::fs::read(path).map_err(|source| DatasetError::Io {
        path: name.clone(),
        source,
    })?;
    parse(&bytes).map_err(|reason| DatasetError::Format { path: name, reason })
}

/// Parses PCD bytes; errors are plain reasons, [`read_pcd`] adds the path. Header and data
/// in one pass because the header decides how the data is laid out (ascii, binary, field
/// sizes and counts), and every length is checked against the bytes before use.
fn parse(bytes: &[u8]) -> Result<(Scan, Vec<String>), String> {
    let mut notes = Vec::new();
    let mut pos = 0usize;
    let (mut names, mut sizes, mut kinds, mut counts) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let (mut width, mut height, mut points) = (None, None, None);
    let data = loop {
        let Some(len) = bytes[pos..].iter().position(|&b| b == b'\n') else {
            return Err("header ends before its DATA line".into());
        };
        let line = std::str::from_utf8(&bytes[pos..pos + len])
            .map_err(|_| "header is not text")?
            .trim();
        pos += len + 1;
        let mut words = line.split_whitespace();
        let Some(key) = words.next() else { continue };
        let rest: Vec<&str> = words.collect();
        let number = |what: &str| -> Result<usize, String> {
            rest.first()
                .and_then(|v| v.parse().ok())
                .ok_or(format!("{what} is not a number: '{line}'"))
        };
        let numbers = || -> Result<Vec<usize>, String> {
            rest.iter()
                .map(|v| v.parse().map_err(|_| format!("not a number in '{line}'")))
                .collect()
        };
        match key.to_ascii_uppercase().as_str() {
            k if k.starts_with('#') => {}
            "VERSION" | "VIEWPOINT" => {}
            "FIELDS" => names = rest.iter().map(|s| s.to_string()).collect(),
            "SIZE" => sizes = numbers()?,
            "TYPE" => {
                kinds = rest
                    .iter()
                    .map(|s| s.bytes().next().unwrap_or(b'?').to_ascii_uppercase())
                    .collect()
            }
            "COUNT" => counts = numbers()?,
            "WIDTH" => width = Some(number("WIDTH")?),
            "HEIGHT" => height = Some(number("HEIGHT")?),
            "POINTS" => points = Some(number("POINTS")?),
            "DATA" => {
                break rest
                    .first()
                    .map(|s| s.to_ascii_lowercase())
                    .unwrap_or_default();
            }
            other => return Err(format!("unknown header line '{other}'")),
        }
    };
    if counts.is_empty() {
        counts = vec![1; names.len()];
    }
    if names.is_empty()
        || sizes.len() != names.len()
        || kinds.len() != names.len()
        || counts.len() != names.len()
    {
        return Err(format!(
            "FIELDS/SIZE/TYPE/COUNT disagree: {} names, {} sizes, {} types, {} counts",
            names.len(),
            sizes.len(),
            kinds.len(),
            counts.len()
        ));
    }
    let (width, height) = (width.ok_or("no WIDTH")?, height.unwrap_or(1).max(1));
    let n = points.unwrap_or(width.saturating_mul(height));
    if n != width.saturating_mul(height) {
        return Err(format!("POINTS {n} != WIDTH {width} x HEIGHT {height}"));
    }
    let mut fields = Vec::with_capacity(names.len());
    let (mut offset, mut column) = (0usize, 0usize);
    for (((name, &size), &kind), &count) in names.iter().zip(&sizes).zip(&kinds).zip(&counts) {
        fields.push(Field {
            name: name.to_ascii_lowercase(),
            size,
            kind,
            offset,
            column,
        });
        offset += size.saturating_mul(count);
        column += count;
    }
    let record = offset;
    let find = |candidates: &[&str]| {
        fields
            .iter()
            .find(|f| candidates.contains(&f.name.as_str()))
            .cloned()
    };
    let (Some(fx), Some(fy), Some(fz)) = (find(&["x"]), find(&["y"]), find(&["z"])) else {
        return Err(format!("no x/y/z fields (found: {})", names.join(", ")));
    };
    let fi = find(&["intensity", "reflectivity", "reflectance"]);
    let fring = find(&["ring", "channel", "laser_id"]);
    let flabel = find(&["label"]);
    for f in [&fx, &fy, &fz] {
        if f.kind != b'F' || !(f.size == 4 || f.size == 8) {
            return Err(format!("field {} must be float32 or float64", f.name));
        }
    }
    for f in [&fx, &fy, &fz]
        .into_iter()
        .chain(&fi)
        .chain(&fring)
        .chain(&flabel)
    {
        if f.decode(&vec![0u8; f.size]).is_none() {
            return Err(format!(
                "field {}: unsupported type {}{}",
                f.name, f.kind as char, f.size
            ));
        }
    }

    // One reader per encoding: `get` returns a field's (first) value for a point.
    let body = &bytes[pos..];
    let mut values: Vec<Vec<f64>> = Vec::new();
    let read_point =
        |get: &dyn Fn(&Field) -> Option<f64>, values: &mut Vec<Vec<f64>>| -> Option<()> {
            let mut row = vec![get(&fx)?, get(&fy)?, get(&fz)?];
            for f in [&fi, &fring, &flabel] {
                row.push(match f {
                    Some(f) => get(f)?,
                    None => 0.0,
                });
            }
            values.push(row);
            Some(())
        };
    match data.as_str() {
        "binary" => {
            let need = n.checked_mul(record).ok_or("size overflows")?;
            if body.len() < need {
                return Err(format!(
                    "binary data holds {} bytes, {n} points of {record} bytes need {need}",
                    body.len()
                ));
            }
            for rec in body[..need].chunks_exact(record.max(1)) {
                let get = |f: &Field| f.decode(rec.get(f.offset..f.offset + f.size)?);
                read_point(&get, &mut values).ok_or("unreadable binary record")?;
            }
            if body.len() > need {
                notes.push(format!(
                    "{} bytes after the last of POINTS {n} ignored",
                    body.len() - need
                ));
            }
        }
        "ascii" => {
            let text = std::str::from_utf8(body).map_err(|_| "ascii data is not text")?;
            let mut lines = text.lines().filter(|l| !l.trim().is_empty());
            for (k, line) in lines.by_ref().take(n).enumerate() {
                let tokens: Vec<&str> = line.split_whitespace().collect();
                let get = |f: &Field| tokens.get(f.column)?.parse::<f64>().ok();
                read_point(&get, &mut values)
                    .ok_or(format!("point {k}: unreadable line '{line}'"))?;
            }
            if values.len() != n {
                return Err(format!(
                    "ascii data holds {} points, the header says {n}",
                    values.len()
                ));
            }
            let extra = lines.count();
            if extra > 0 {
                notes.push(format!(
                    "{extra} lines after the last of POINTS {n} ignored"
                ));
            }
        }
        other => {
            return Err(format!(
                "DATA {other} is not supported (ascii and binary are); convert with pcl_convert_pcd_ascii_binary"
            ));
        }
    }

    let xyz = values
        .iter()
        .map(|v| [v[0] as f32, v[1] as f32, v[2] as f32])
        .collect();
    let mut scan = Scan {
        xyz,
        height,
        width,
        ..Default::default()
    };
    if fi.is_some() {
        scan.intensity = Some(values.iter().map(|v| v[3] as f32).collect());
    }
    if let Some(f) = &fring {
        let ring: Vec<f64> = values.iter().map(|v| v[4]).collect();
        match ring_ids(&ring, |i| scan.is_return(i)) {
            Ok(ids) => scan.ring = Some(ids),
            Err(bad) => notes.push(format!(
                "ring field \"{}\" holds {bad} non-finite values at returns; rows taken from the cloud's order or elevation instead",
                f.name
            )),
        }
    }
    if flabel.is_some() {
        scan.label = Some(
            values
                .iter()
                .map(|v| v[5].clamp(0.0, f64::from(u32::MAX)) as u32)
                .collect(),
        );
    }
    Ok((scan, notes))
}

#[cfg(test)]
mod tests {
    use super::*;

    const HEADER: &str = "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z intensity channel\nSIZE 4 4 4 1 2\nTYPE F F F U U\nCOUNT 1 1 1 1 1\nWIDTH 2\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 2\n";

    #[test]
    fn ascii_and_binary_give_the_same_scan() {
        let ascii = format!("{HEADER}DATA ascii\n1.5 -2 3 10 7\n4 5 -6.25 200 15\n");
        let (a, notes) = parse(ascii.as_bytes()).unwrap();
        assert!(notes.is_empty(), "{notes:?}");
        let mut bin = format!("{HEADER}DATA binary\n").into_bytes();
        for (p, i, c) in [
            ([1.5f32, -2.0, 3.0], 10u8, 7u16),
            ([4.0, 5.0, -6.25], 200, 15),
        ] {
            p.iter()
                .for_each(|v| bin.extend_from_slice(&v.to_le_bytes()));
            bin.push(i);
            bin.extend_from_slice(&c.to_le_bytes());
        }
        let (b, _) = parse(&bin).unwrap();
        assert_eq!(a, b);
        assert_eq!(a.xyz, vec![[1.5, -2.0, 3.0], [4.0, 5.0, -6.25]]);
        assert_eq!(a.intensity, Some(vec![10.0, 200.0]));
        assert_eq!(a.ring, Some(vec![7, 15]));
        assert!(!a.is_organized());
    }

    #[test]
    fn bad_files_are_errors_not_panics() {
        let short = format!("{HEADER}DATA binary\n\x01\x02");
        assert!(parse(short.as_bytes()).unwrap_err().contains("need 30"));
        let lzf = format!("{HEADER}DATA binary_compressed\n");
        assert!(
            parse(lzf.as_bytes())
                .unwrap_err()
                .contains("binary_compressed is not supported")
        );
        let no_z = HEADER.replace("x y z", "x y q");
        assert!(
            parse(format!("{no_z}DATA ascii\n").as_bytes())
                .unwrap_err()
                .contains("no x/y/z")
        );
        assert!(
            parse(b"VERSION 0.7\nFIELDS x")
                .unwrap_err()
                .contains("before its DATA")
        );
        let few = format!("{HEADER}DATA ascii\n1 2 3 4 5\n");
        assert!(
            parse(few.as_bytes())
                .unwrap_err()
                .contains("holds 1 points")
        );

        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("bad.pcd");
        std::fs::write(&path, lzf).unwrap();
        assert!(read_pcd(&path).unwrap_err().to_string().contains("bad.pcd"));
    }

    /// A float ring field of 0, 0.5, 1, ... keeps 32 rings apart, as do negative rings; a NaN
    /// ring at a return leaves the field unused with a note; data past POINTS is noted.
    #[test]
    fn odd_rings_keep_their_beams_and_extra_data_is_noted() {
        let header = |rings: &str, points: usize| {
            format!(
                "VERSION 0.7\nFIELDS x y z ring\nSIZE 4 4 4 4\nTYPE F F F F\nWIDTH {points}\nHEIGHT 1\nPOINTS {points}\nDATA ascii\n{rings}"
            )
        };
        let lines = |rings: &[f32]| -> String {
            rings
                .iter()
                .enumerate()
                .map(|(k, r)| format!("{} 1 0.5 {r}\n", 5.0 + k as f32))
                .collect()
        };
        let halves: Vec<f32> = (0..32).map(|k| k as f32 * 0.5).collect();
        let (scan, notes) = parse(header(&lines(&halves), 32).as_bytes()).unwrap();
        let mut rings = scan.ring.clone().unwrap();
        rings.dedup();
        assert_eq!(rings.len(), 32, "{rings:?}");
        assert!(notes.is_empty());
        let negative: Vec<f32> = (0..16).map(|k| k as f32 - 8.0).collect();
        let (scan, _) = parse(header(&lines(&negative), 16).as_bytes()).unwrap();
        assert_eq!(scan.ring.unwrap()[..3], [0, 1, 2]);
        let nan = [1.0, f32::NAN, 2.0];
        let (scan, notes) = parse(header(&lines(&nan), 3).as_bytes()).unwrap();
        assert!(scan.ring.is_none());
        assert!(notes[0].contains("non-finite"), "{notes:?}");
        // Two lines more than POINTS.
        let extra = header(&lines(&[0.0, 1.0, 2.0, 3.0]), 2);
        let (scan, notes) = parse(extra.as_bytes()).unwrap();
        assert_eq!(scan.len(), 2);
        assert!(
            notes[0].contains("2 lines after the last of POINTS 2"),
            "{notes:?}"
        );
        let mut bin = HEADER.as_bytes().to_vec();
        bin.extend_from_slice(b"DATA binary\n");
        bin.extend(std::iter::repeat_n(0u8, 2 * 15 + 7));
        let (_, notes) = parse(&bin).unwrap();
        assert!(notes[0].contains("7 bytes after"), "{notes:?}");
    }
}
