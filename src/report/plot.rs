//! The report's pictures as PNG bytes: line charts drawn with `plotters` (axes,
//! tick labels, title, legend; text in the bundled DejaVu Sans, so no system font
//! is needed) and plain false-colour pixel images (viridis); the `png` crate
//! encodes both. Also owns the font registration the examples and benches share,
//! and the atomic file write every report file goes through.

use std::sync::OnceLock;

use anyhow::Context;
use plotters::prelude::*;
use plotters::style::colors::colormaps::{ColorMap, ViridisRGB};

pub type Rgb = [u8; 3];

/// Series colours: real, sim, sim + fitted (#d62728, #1f77b4, #2ca02c).
pub const REAL: RGBColor = RGBColor(214, 39, 40);
pub const SIM: RGBColor = RGBColor(31, 119, 180);
pub const FITTED: RGBColor = RGBColor(44, 160, 44);

/// Size of a line chart in pixels.
pub const CHART_SIZE: (u32, u32) = (800, 450);

/// DejaVu Sans (licence: assets/fonts/LICENSE-DejaVu.txt).
static FONT: &[u8] = include_bytes!("../../assets/fonts/DejaVuSans.ttf");

/// Registers the bundled DejaVu Sans as plotters' "sans-serif" (once; later
/// calls do nothing). Charts drawn before this have no font and fail to draw.
pub fn register_font() {
    static REGISTERED: OnceLock<()> = OnceLock::new();
    REGISTERED.get_or_init(|| {
        // The bundled bytes are a valid font (the tests draw text with it); were
        // they not, drawing text would fail with an error, never a panic.
        let _ = plotters::style::register_font("sans-serif", FontStyle::Normal, FONT);
    });
}

/// One line of a chart: y per x of the chart, NaN = gap.
#[derive(Debug, Clone, Copy)]
pub struct Series<'a> {
    pub label: &'a str,
    pub colour: RGBColor,
    pub y: &'a [f64],
}

/// A line chart: `series` over `x` (ascending). The y axis starts at 0 and leaves
/// headroom above the data for the legend in the upper left.
#[derive(Debug, Clone, Copy)]
pub struct LineChart<'a> {
    pub title: &'a str,
    pub x_label: &'a str,
    pub y_label: &'a str,
    pub x: &'a [f64],
    /// In legend order; the first is drawn on top.
    pub series: &'a [Series<'a>],
}

/// Draws `chart` (`CHART_SIZE`) and returns it as PNG bytes.
pub fn line_chart(chart: &LineChart) -> anyhow::Result<Vec<u8>> {
    register_font();
    let finite = |v: &[f64]| {
        v.iter()
            .copied()
            .filter(|y| y.is_finite())
            .collect::<Vec<_>>()
    };
    let xs = finite(chart.x);
    let x_min = xs.iter().copied().fold(f64::INFINITY, f64::min);
    let x_max = xs.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let (x_min, x_max) = match (x_min.is_finite(), x_max > x_min) {
        (true, true) => (x_min, x_max),
        (true, false) => (x_min - 0.5, x_min + 0.5),
        (false, _) => (0.0, 1.0),
    };
    let y_max = chart
        .series
        .iter()
        .flat_map(|s| finite(s.y))
        .fold(0.0f64, f64::max)
        .max(0.01)
        * 1.35;

    let (w, h) = CHART_SIZE;
    let mut buf = vec![255u8; (w * h * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        root.fill(&WHITE)?;
        let mut c = ChartBuilder::on(&root)
            .caption(chart.title, ("sans-serif", 20))
            .margin(12)
            .x_label_area_size(48)
            .y_label_area_size(64)
            .build_cartesian_2d(x_min..x_max, 0.0..y_max)?;
        c.configure_mesh()
            .x_desc(chart.x_label)
            .y_desc(chart.y_label)
            .label_style(("sans-serif", 14))
            .axis_desc_style(("sans-serif", 15))
            .draw()?;
        // Legend entries (empty series, so a series without data is still named).
        for s in chart.series {
            let colour = s.colour;
            c.draw_series(LineSeries::new(std::iter::empty(), colour.stroke_width(2)))?
                .label(s.label)
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(3))
                });
        }
        for s in chart.series.iter().rev() {
            let points: Vec<(f64, f64)> =
                chart.x.iter().copied().zip(s.y.iter().copied()).collect();
            for run in points.split(|p| !(p.0.is_finite() && p.1.is_finite())) {
                if run.is_empty() {
                    continue;
                }
                // A point between two gaps is a dot.
                let dot = if run.len() == 1 { 3 } else { 0 };
                c.draw_series(
                    LineSeries::new(run.iter().copied(), s.colour.stroke_width(2)).point_size(dot),
                )?;
            }
        }
        c.configure_series_labels()
            .position(SeriesLabelPosition::UpperLeft)
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .label_font(("sans-serif", 14))
            .draw()?;
        root.present()?;
    }
    crate::util::png::encode_rgb(w, h, &buf)
}

/// A range-image map with axes (azimuth along x, beam row down y), a title and,
/// for a scalar map, a viridis colour bar from 0 to `colour_bar.0`.
pub struct MapChart<'a> {
    pub title: &'a str,
    pub height: usize,
    pub width: usize,
    /// Colour of pixel `k` (row-major).
    pub colour: &'a dyn Fn(usize) -> Rgb,
    /// (value at the top of the bar, its label); None: no bar (a legend in the
    /// caption says what the colours mean).
    pub colour_bar: Option<(f32, &'a str)>,
}

/// Size of a map chart in pixels.
pub const MAP_SIZE: (u32, u32) = (1000, 420);

/// Draws `map` (`MAP_SIZE`) and returns it as PNG bytes.
pub fn map_chart(map: &MapChart) -> anyhow::Result<Vec<u8>> {
    register_font();
    let (w, h) = MAP_SIZE;
    let (rows, cols) = (map.height.max(1), map.width.max(1));
    let mut buf = vec![255u8; (w * h * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        root.fill(&WHITE)?;
        let root = root.titled(map.title, ("sans-serif", 20))?;
        let (left, right) = root.split_horizontally(w - 110);
        let mut c = ChartBuilder::on(&left)
            .margin(10)
            .x_label_area_size(44)
            .y_label_area_size(56)
            .build_cartesian_2d(0f64..cols as f64, rows as f64..0f64)?;
        // Columns run from azimuth +180 deg (left) to -180 deg (right).
        let azimuth = |j: &f64| format!("{:.0}", 180.0 - j * 360.0 / cols as f64);
        c.configure_mesh()
            .disable_mesh()
            .x_desc("azimuth (deg; 0 = straight ahead)")
            .y_desc("beam row (0 = top)")
            .x_labels(9)
            .x_label_formatter(&azimuth)
            .y_label_formatter(&|r: &f64| format!("{r:.0}"))
            .label_style(("sans-serif", 13))
            .axis_desc_style(("sans-serif", 14))
            .draw()?;
        c.draw_series((0..rows * cols).map(|k| {
            let (i, j) = ((k / cols) as f64, (k % cols) as f64);
            let [r, g, b] = (map.colour)(k);
            Rectangle::new([(j, i), (j + 1.0, i + 1.0)], RGBColor(r, g, b).filled())
        }))?;
        if let Some((top, label)) = map.colour_bar {
            let top = f64::from(top.max(1e-6));
            let mut bar = ChartBuilder::on(&right)
                .margin_top(10)
                .margin_bottom(54)
                .margin_right(10)
                .y_label_area_size(62)
                .build_cartesian_2d(0f64..1f64, 0f64..top)?;
            bar.configure_mesh()
                .disable_mesh()
                .disable_x_axis()
                .y_desc(label)
                .y_labels(6)
                .label_style(("sans-serif", 12))
                .axis_desc_style(("sans-serif", 13))
                .draw()?;
            let steps = 100;
            bar.draw_series((0..steps).map(|s| {
                let (a, b) = (s as f64 / steps as f64, (s + 1) as f64 / steps as f64);
                let [r, g, bl] = viridis(((a + b) / 2.0) as f32);
                Rectangle::new(
                    [(0.0, a * top), (1.0, b * top)],
                    RGBColor(r, g, bl).filled(),
                )
            }))?;
        }
        root.present()?;
    }
    crate::util::png::encode_rgb(w, h, &buf)
}

/// Viridis (dark purple 0, yellow 1) for `v` clamped to [0, 1]; NaN is white.
pub fn viridis(v: f32) -> Rgb {
    if v.is_nan() {
        return [255, 255, 255];
    }
    let RGBColor(r, g, b) = ViridisRGB.get_color(v.clamp(0.0, 1.0));
    [r, g, b]
}

/// An `h` x `w` pixel image (row-major, pixel `k` coloured by `colour(k)`), each
/// row repeated `row_scale` times, as PNG bytes.
pub fn image(
    h: usize,
    w: usize,
    row_scale: usize,
    colour: impl Fn(usize) -> Rgb,
) -> anyhow::Result<Vec<u8>> {
    let row_scale = row_scale.max(1);
    let mut buf = Vec::with_capacity(h * row_scale * w * 3);
    for i in 0..h {
        let row: Vec<u8> = (0..w).flat_map(|j| colour(i * w + j)).collect();
        for _ in 0..row_scale {
            buf.extend_from_slice(&row);
        }
    }
    let size = |n: usize| u32::try_from(n).context("image too large");
    crate::util::png::encode_rgb(size(w)?, size(h * row_scale)?, &buf)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn decode(png_bytes: &[u8]) -> (u32, u32, Vec<Rgb>) {
        let mut reader = png::Decoder::new(std::io::Cursor::new(png_bytes))
            .read_info()
            .unwrap();
        let mut buf = vec![0; reader.output_buffer_size().unwrap()];
        let info = reader.next_frame(&mut buf).unwrap();
        assert_eq!(
            (info.color_type, info.bit_depth),
            (png::ColorType::Rgb, png::BitDepth::Eight)
        );
        let pixels = buf[..info.buffer_size()]
            .chunks_exact(3)
            .map(|p| [p[0], p[1], p[2]])
            .collect();
        (info.width, info.height, pixels)
    }

    #[test]
    fn chart_has_text_series_and_gaps() {
        let x: Vec<f64> = (0..10).map(f64::from).collect();
        let real = [0.1, 0.2, 0.3, 0.4, 0.5, 0.6, f64::NAN, f64::NAN, 0.9, 1.0];
        let sim = [0.3; 10];
        let fitted = [0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9];
        let png_bytes = line_chart(&LineChart {
            title: "Drop rate against range",
            x_label: "range (m)",
            y_label: "drop rate",
            x: &x,
            series: &[
                Series {
                    label: "real",
                    colour: REAL,
                    y: &real,
                },
                Series {
                    label: "sim",
                    colour: SIM,
                    y: &sim,
                },
                Series {
                    label: "fitted",
                    colour: FITTED,
                    y: &fitted,
                },
            ],
        })
        .unwrap();
        let (w, h, px) = decode(&png_bytes);
        assert_eq!((w, h), CHART_SIZE);
        let at = |x: u32, y: u32| px[(y * w + x) as usize];
        let [c_real, c_sim, c_fitted] = [REAL, SIM, FITTED].map(|c| [c.0, c.1, c.2]);
        // Each series is a line across the plot, far more than its legend sample.
        for c in [c_real, c_sim, c_fitted] {
            let n = px.iter().filter(|&&p| p == c).count();
            assert!(n > 600, "{c:?}: {n} pixels");
        }
        // Text: dark pixels left of the y axis (tick labels, "drop rate"), below
        // the x axis (tick labels, "range (m)") and in the title strip above the
        // middle of the plot.
        let dark = |xs: std::ops::Range<u32>, ys: std::ops::Range<u32>| {
            ys.flat_map(|y| xs.clone().map(move |x| (x, y)))
                .filter(|&(x, y)| at(x, y).iter().all(|&v| v < 100))
                .count()
        };
        assert!(dark(0..60, 40..h - 60) > 100, "y tick labels");
        assert!(dark(80..w, h - 40..h) > 100, "x tick labels");
        assert!(dark(w / 2 - 150..w / 2 + 150, 0..30) > 100, "title");
        // The sim line spans the plot: map x to columns by its ends, then the
        // real series has no pixel in the gap between x = 5 and x = 8.
        let sim_cols: Vec<u32> = (0..w)
            .filter(|&x| (0..h).any(|y| at(x, y) == c_sim))
            .collect();
        let (first, last) = (sim_cols[0] as f64, *sim_cols.last().unwrap() as f64);
        let col = |v: f64| (first + v / 9.0 * (last - first)) as u32;
        let real_in = |xs: std::ops::Range<u32>| {
            xs.flat_map(|x| (0..h).map(move |y| (x, y)))
                .any(|(x, y)| at(x, y) == c_real)
        };
        assert!(!real_in(col(5.3)..col(7.7)), "gap drawn");
        assert!(real_in(col(3.3)..col(4.7)), "no real line");
    }

    #[test]
    fn images_are_pixels_in_viridis() {
        let png_bytes = image(2, 3, 2, |k| {
            if k == 5 {
                viridis(f32::NAN)
            } else {
                viridis(k as f32 / 4.0)
            }
        })
        .unwrap();
        let (w, h, px) = decode(&png_bytes);
        assert_eq!((w, h), (3, 4));
        assert_eq!(px[0], [68, 1, 84]);
        assert_eq!(px[3], px[0], "rows repeated");
        assert_eq!(px[6], viridis(0.75));
        assert_eq!(px[7], [254, 232, 37]);
        assert_eq!(px[11], [255, 255, 255], "NaN is white");
        assert_eq!(viridis(2.0), viridis(1.0));
    }
}
