//! How much a local rule could gain over the inverse-depth blend of the kept beams above and
//! below a restored pixel: per pixel, the best of the blend, either side's depth and the line
//! through either side's two beams (an oracle that knows the truth), near (<= 30 m true
//! depth) and far, on every third scan of the validation drive (never the held-out scans).
//! Pixels whose column has no kept return on one side are left out (the fills differ there).
//!
//!     cargo run --release --example fill_oracle -- [../shared/real_lidar] [16 | 8 kept lines]
use std::path::PathBuf;

use anyhow::Result;
use rangegan_mcap::decode::Sparsify;
use rangegan_mcap::model::data::kitti_validation_split;
use rangegan_mcap::train::row_fill::kitti_depth;

#[derive(Default, Debug)]
struct Sums {
    n: usize,
    blend: f64,
    above: f64,
    below: f64,
    nearer_row: f64,
    oracle: f64,
    line: f64,
    oracle3: f64,
    smooth_n: usize,
    smooth_blend: f64,
    edge_n: usize,
    edge_blend: f64,
    edge_nearer: f64,
    edge_oracle: f64,
    edge_front: f64,
    edge_back: f64,
}

fn main() -> Result<()> {
    let data = PathBuf::from(
        std::env::args()
            .nth(1)
            .unwrap_or("../shared/real_lidar".into()),
    );
    let lines: usize = std::env::args().nth(2).map_or(16, |s| s.parse().unwrap());
    let (_, files) = kitti_validation_split(&data, &["kitti_raw_drive_d".to_string()])?;
    let kept = Sparsify::kept_rows(lines, 64);
    let (mut near, mut far) = (Sums::default(), Sums::default());
    for f in files.iter().step_by(3) {
        let (grid, d) = kitti_depth(f)?;
        let el = &grid.elevation_rad;
        let w = 512;
        for c in 0..w {
            for r in 0..64 {
                let t = d[r * w + c];
                if t <= 0.0 || kept.contains(&r) {
                    continue;
                }
                let ia = kept.iter().rposition(|&q| q < r);
                let ib = kept.iter().position(|&q| q > r);
                let (Some(ia), Some(ib)) = (ia, ib) else {
                    continue;
                };
                let (a, b) = (kept[ia], kept[ib]);
                let (da, db) = (d[a * w + c], d[b * w + c]);
                if da <= 0.0 || db <= 0.0 {
                    continue;
                }
                let (ea, eb, e) = (el[a * w + c], el[b * w + c], el[r * w + c]);
                let s = ((e - ea) / (eb - ea)).clamp(0.0, 1.0);
                let blend = 1.0 / ((1.0 - s) / da + s / db);
                let nearer = if r - a <= b - r { da } else { db };
                // Line through the outer neighbour and the near one, on each side, in the
                // column's (horizontal distance, height) plane, met by the pixel's ray.
                let pt = |row: usize| {
                    let dd = d[row * w + c];
                    (dd * el[row * w + c].cos(), dd * el[row * w + c].sin())
                };
                let meet = |p: (f32, f32), q: (f32, f32)| -> Option<f32> {
                    // ray: (t cos e, t sin e); line: p + u (q - p)
                    let (dx, dz) = (q.0 - p.0, q.1 - p.1);
                    let (ce, se) = (e.cos(), e.sin());
                    let den = ce * dz - se * dx;
                    if den.abs() < 1e-9 {
                        return None;
                    }
                    let tt = (p.0 * dz - p.1 * dx) / den;
                    (tt > 0.0).then_some(tt)
                };
                let ext_a = ia
                    .checked_sub(1)
                    .map(|k| kept[k])
                    .filter(|&q| d[q * w + c] > 0.0)
                    .and_then(|q| meet(pt(q), pt(a)));
                let ext_b = kept
                    .get(ib + 1)
                    .filter(|&&q| d[q * w + c] > 0.0)
                    .and_then(|&q| meet(pt(b), pt(q)));
                let jump = (da / db).ln().abs();
                let sums = if t <= 30.0 { &mut near } else { &mut far };
                let err = |v: f32| f64::from((v - t).abs());
                sums.n += 1;
                sums.blend += err(blend);
                sums.above += err(da);
                sums.below += err(db);
                sums.nearer_row += err(nearer);
                sums.oracle += err(blend).min(err(da)).min(err(db));
                let line = match (ext_a, ext_b) {
                    (Some(x), _) if r - a <= b - r => x,
                    (_, Some(x)) => x,
                    _ => blend,
                };
                sums.line += err(line);
                sums.oracle3 += [Some(blend), Some(da), Some(db), ext_a, ext_b]
                    .iter()
                    .flatten()
                    .map(|&v| err(v))
                    .fold(f64::INFINITY, f64::min);
                if jump < 0.1 {
                    sums.smooth_n += 1;
                    sums.smooth_blend += err(blend);
                } else {
                    sums.edge_n += 1;
                    sums.edge_blend += err(blend);
                    sums.edge_nearer += err(nearer);
                    sums.edge_oracle += err(da).min(err(db));
                    sums.edge_front += err(da.min(db));
                    sums.edge_back += err(da.max(db));
                }
            }
        }
    }
    for (name, s) in [("near", near), ("far", far)] {
        let m = |v: f64, n: usize| v / n.max(1) as f64;
        println!(
            "{name}: n {} | blend {:.3} above {:.3} below {:.3} nearer-row {:.3} line {:.3} | oracle(blend,a,b) {:.3} oracle(+lines) {:.3}",
            s.n,
            m(s.blend, s.n),
            m(s.above, s.n),
            m(s.below, s.n),
            m(s.nearer_row, s.n),
            m(s.line, s.n),
            m(s.oracle, s.n),
            m(s.oracle3, s.n)
        );
        println!(
            "   smooth (jump<0.1) n {} blend {:.3} | edges n {} blend {:.3} nearer-row {:.3} front {:.3} back {:.3} oracle side {:.3} | share of blend error at edges {:.2}",
            s.smooth_n,
            m(s.smooth_blend, s.smooth_n),
            s.edge_n,
            m(s.edge_blend, s.edge_n),
            m(s.edge_nearer, s.edge_n),
            m(s.edge_front, s.edge_n),
            m(s.edge_back, s.edge_n),
            m(s.edge_oracle, s.edge_n),
            s.edge_blend / s.blend.max(1e-9)
        );
    }
    Ok(())
}
