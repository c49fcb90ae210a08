//! A tiny RGB canvas written as PNG with the `png` crate: line charts (axes, grid
//! ticks, polylines) and false-colour images. No text: titles, axis ranges and
//! legends go in the HTML beside each image, so no system font is needed.

use std::io::Write;

pub type Rgb = [u8; 3];

pub const WHITE: Rgb = [255, 255, 255];
pub const GREY: Rgb = [200, 200, 200];
pub const BLACK: Rgb = [0, 0, 0];
/// Series colours: real, sim, sim + fitted.
pub const REAL: Rgb = [214, 39, 40];
pub const SIM: Rgb = [31, 119, 180];
pub const FITTED: Rgb = [44, 160, 44];

pub struct Canvas {
    pub width: usize,
    pub height: usize,
    pixels: Vec<Rgb>,
}

impl Canvas {
    pub fn new(width: usize, height: usize, background: Rgb) -> Self {
        Canvas {
            width,
            height,
            pixels: vec![background; width * height],
        }
    }

    pub fn set(&mut self, x: i64, y: i64, c: Rgb) {
        if x >= 0 && y >= 0 && (x as usize) < self.width && (y as usize) < self.height {
            self.pixels[y as usize * self.width + x as usize] = c;
        }
    }

    /// A line `thickness` pixels wide (Bresenham, stamped).
    pub fn line(&mut self, (x0, y0): (i64, i64), (x1, y1): (i64, i64), c: Rgb, thickness: i64) {
        let (dx, dy) = ((x1 - x0).abs(), -(y1 - y0).abs());
        let (sx, sy) = (if x0 < x1 { 1 } else { -1 }, if y0 < y1 { 1 } else { -1 });
        let (mut x, mut y, mut err) = (x0, y0, dx + dy);
        let r = thickness / 2;
        loop {
            for ox in -r..=r {
                for oy in -r..=r {
                    self.set(x + ox, y + oy, c);
                }
            }
            if x == x1 && y == y1 {
                break;
            }
            let e2 = 2 * err;
            if e2 >= dy {
                err += dy;
                x += sx;
            }
            if e2 <= dx {
                err += dx;
                y += sy;
            }
        }
    }

    /// PNG bytes (8-bit RGB).
    pub fn png(&self) -> Vec<u8> {
        let mut out = Vec::new();
        {
            let mut enc = png::Encoder::new(&mut out, self.width as u32, self.height as u32);
            enc.set_color(png::ColorType::Rgb);
            enc.set_depth(png::BitDepth::Eight);
            let data: Vec<u8> = self.pixels.iter().flatten().copied().collect();
            if let Ok(mut w) = enc.write_header() {
                let _ = w.write_image_data(&data);
            }
        }
        out
    }
}

/// Axis ranges of a chart.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Axes {
    pub x_min: f64,
    pub x_max: f64,
    pub y_min: f64,
    pub y_max: f64,
}

/// A line chart of `series` (colour, y per x; NaN = gap) over `x`, with a frame
/// and ten grid ticks per axis.
pub fn line_chart(x: &[f64], series: &[(Rgb, &[f64])], axes: Axes) -> Canvas {
    let (w, h, margin) = (640i64, 360i64, 24i64);
    let mut c = Canvas::new(w as usize, h as usize, WHITE);
    let px = |v: f64| {
        margin
            + ((v - axes.x_min) / (axes.x_max - axes.x_min).max(1e-12) * (w - 2 * margin) as f64)
                as i64
    };
    let py = |v: f64| {
        h - margin
            - ((v - axes.y_min) / (axes.y_max - axes.y_min).max(1e-12) * (h - 2 * margin) as f64)
                as i64
    };
    for t in 0..=10 {
        let gx = margin + t * (w - 2 * margin) / 10;
        let gy = margin + t * (h - 2 * margin) / 10;
        c.line((gx, margin), (gx, h - margin), GREY, 1);
        c.line((margin, gy), (w - margin, gy), GREY, 1);
    }
    c.line((margin, h - margin), (w - margin, h - margin), BLACK, 1);
    c.line((margin, margin), (margin, h - margin), BLACK, 1);
    for (colour, y) in series {
        let mut last: Option<(i64, i64)> = None;
        for (xi, yi) in x.iter().zip(y.iter()) {
            if !yi.is_finite() {
                last = None;
                continue;
            }
            let p = (px(*xi), py(yi.clamp(axes.y_min, axes.y_max)));
            if let Some(l) = last {
                c.line(l, p, *colour, 3);
            } else {
                c.line(p, p, *colour, 5);
            }
            last = Some(p);
        }
    }
    c
}

/// A perceptual-ish colour ramp (dark blue -> teal -> yellow) for v in [0, 1].
pub fn ramp(v: f32) -> Rgb {
    let v = v.clamp(0.0, 1.0);
    let stops: [(f32, [f32; 3]); 4] = [
        (0.0, [68.0, 1.0, 84.0]),
        (0.33, [49.0, 104.0, 142.0]),
        (0.66, [53.0, 183.0, 121.0]),
        (1.0, [253.0, 231.0, 37.0]),
    ];
    for pair in stops.windows(2) {
        let ((a, ca), (b, cb)) = (pair[0], pair[1]);
        if v <= b {
            let t = (v - a) / (b - a);
            return [0, 1, 2].map(|i| (ca[i] + t * (cb[i] - ca[i])) as u8);
        }
    }
    [253, 231, 37]
}

/// An `h x w` image, each pixel `scale` x `scale` (rows stretched by `row_scale`).
pub fn image(h: usize, w: usize, row_scale: usize, colour: impl Fn(usize) -> Rgb) -> Canvas {
    let mut c = Canvas::new(w, h * row_scale, WHITE);
    for i in 0..h {
        for j in 0..w {
            let col = colour(i * w + j);
            for r in 0..row_scale {
                c.set(j as i64, (i * row_scale + r) as i64, col);
            }
        }
    }
    c
}

/// Writes `bytes` to `path` atomically (temporary file in the same folder, then rename).
pub fn write_atomic(path: &std::path::Path, bytes: &[u8]) -> std::io::Result<()> {
    let tmp = path.with_extension(format!(
        "{}.tmp{}",
        path.extension().and_then(|e| e.to_str()).unwrap_or(""),
        std::process::id()
    ));
    {
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(bytes)?;
        f.sync_all()?;
    }
    std::fs::rename(&tmp, path)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn charts_and_images_encode_as_png() {
        let x = [0.0, 1.0, 2.0, 3.0];
        let y = [0.1, f64::NAN, 0.5, 0.9];
        let c = line_chart(
            &x,
            &[(REAL, &y)],
            Axes {
                x_min: 0.0,
                x_max: 3.0,
                y_min: 0.0,
                y_max: 1.0,
            },
        );
        let png = c.png();
        assert_eq!(&png[1..4], b"PNG");
        let decoder = png::Decoder::new(std::io::Cursor::new(png));
        let reader = decoder.read_info().unwrap();
        assert_eq!((reader.info().width, reader.info().height), (640, 360));
        let img = image(2, 3, 2, |k| ramp(k as f32 / 5.0));
        assert_eq!((img.width, img.height), (3, 4));
        assert_eq!(ramp(0.0), [68, 1, 84]);
        assert_eq!(ramp(1.0), [253, 231, 37]);
    }
}
