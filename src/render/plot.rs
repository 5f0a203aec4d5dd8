//! Plots drawn with `plotters` into a PNG: a subject's history (measurements and weight over
//! time) and x-y curves (a stereo matcher's wrong matches against its coverage). Text is
//! drawn in DejaVu Sans: the system's (Debian's fonts-dejavu-core), or the copy built into
//! the binary (`assets/fonts`, its licence beside it) where the system has none, so a
//! station's plots are never drawn unlabelled.

use plotters::prelude::*;

/// A plot that could not be drawn: plotters' own error, in its words.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct PlotError(String);

impl PlotError {
    fn of(e: impl std::fmt::Display) -> PlotError {
        PlotError(e.to_string())
    }
}

/// One line of a plot: its name, unit and points (x: days since the first result).
pub struct Series {
    pub name: String,
    pub unit: String,
    pub points: Vec<(f64, f64)>,
}

const FONT_FILES: [&str; 2] = [
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu/DejaVuSans.ttf",
];

/// DejaVu Sans as built into the binary, for a system without the font package.
static BUILT_IN_FONT: &[u8] = include_bytes!("../../assets/fonts/DejaVuSans.ttf");

/// The first of `files` that can be read, or the built-in copy.
fn font_bytes(files: &[&str]) -> &'static [u8] {
    files
        .iter()
        .find_map(|p| crate::files::read_limited(p.as_ref(), 64 << 20).ok())
        .map_or(BUILT_IN_FONT, |bytes| Box::leak(bytes.into_boxed_slice()))
}

/// Registers the font once; whether text can be drawn (false only when plotters refuses
/// the font itself).
fn font() -> bool {
    static FONT: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *FONT.get_or_init(|| {
        let bytes = font_bytes(&FONT_FILES);
        plotters::style::register_font("sans-serif", FontStyle::Normal, bytes).is_ok()
            || plotters::style::register_font("sans-serif", FontStyle::Normal, BUILT_IN_FONT)
                .is_ok()
    })
}

/// The time axis for a history spanning `span_days`: the factor from days and its unit,
/// so that an afternoon reads in hours, a season in days and a year in months (one
/// result alone reads in hours around it).
pub fn time_axis(span_days: f64) -> (f64, &'static str) {
    if !(span_days >= 2.0) {
        (24.0, "hours")
    } else if span_days < 180.0 {
        (1.0, "days")
    } else {
        (12.0 / 365.25, "months")
    }
}

/// One panel: `series` as lines with points, axes described by `desc` (x, y) when
/// `text` (a font) is there, a legend at the upper left.
fn draw_panel(
    panel: &DrawingArea<BitMapBackend, plotters::coord::Shift>,
    series: &[&Series],
    desc: (&str, &str),
    text: bool,
) -> Result<(), PlotError> {
    let (mut x0, mut x1, mut y0, mut y1) = (
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::INFINITY,
        f64::NEG_INFINITY,
    );
    for p in series.iter().flat_map(|s| &s.points) {
        x0 = x0.min(p.0);
        x1 = x1.max(p.0);
        y0 = y0.min(p.1);
        y1 = y1.max(p.1);
    }
    if !x0.is_finite() {
        return Ok(());
    }
    let (xpad, ypad) = (
        ((x1 - x0) * 0.05).max(0.5),
        ((y1 - y0) * 0.1).max(y1.abs() * 0.01 + 1e-9),
    );
    let mut b = ChartBuilder::on(panel);
    b.margin(8);
    if text {
        b.x_label_area_size(28).y_label_area_size(56);
    }
    let mut chart = b
        .build_cartesian_2d((x0 - xpad)..(x1 + xpad), (y0 - ypad)..(y1 + ypad))
        .map_err(PlotError::of)?;
    let mut mesh = chart.configure_mesh();
    if text {
        mesh.x_desc(desc.0).y_desc(desc.1);
    } else {
        mesh.disable_x_axis().disable_y_axis();
    }
    mesh.draw().map_err(PlotError::of)?;
    let colours = [RED, BLUE, GREEN, MAGENTA, CYAN, BLACK];
    for (k, s) in series.iter().enumerate() {
        let c = colours[k % colours.len()];
        let drawn = chart
            .draw_series(LineSeries::new(s.points.iter().copied(), c.stroke_width(2)))
            .map_err(PlotError::of)?;
        if text {
            drawn.label(s.name.clone()).legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 16, y)], c.stroke_width(2))
            });
        }
        chart
            .draw_series(s.points.iter().map(|&p| Circle::new(p, 3, c.filled())))
            .map_err(PlotError::of)?;
    }
    if text {
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .position(SeriesLabelPosition::UpperLeft)
            .draw()
            .map_err(PlotError::of)?;
    }
    Ok(())
}

/// A PNG of `series` in one panel, x and y described by `desc`, `title` above: e.g. a
/// stereo matcher's wrong matches against its coverage.
pub fn xy_png(
    title: &str,
    desc: (&str, &str),
    series: &[Series],
    width: u32,
    height: u32,
) -> Result<Vec<u8>, PlotError> {
    let mine: Vec<&Series> = series.iter().collect();
    drawn_png(title, width, height, |area, text| {
        draw_panel(area, &mine, desc, text)
    })
}

/// A `width` x `height` PNG drawn by `draw` (given the area under `title` and whether
/// text can be drawn).
fn drawn_png(
    title: &str,
    width: u32,
    height: u32,
    draw: impl FnOnce(
        &DrawingArea<BitMapBackend, plotters::coord::Shift>,
        bool,
    ) -> Result<(), PlotError>,
) -> Result<Vec<u8>, PlotError> {
    let text = font();
    let mut buf = vec![255u8; (width * height * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (width, height)).into_drawing_area();
        let area = if text {
            root.titled(title, ("sans-serif", 18))
                .map_err(PlotError::of)?
        } else {
            root.clone()
        };
        draw(&area, text)?;
        root.present().map_err(PlotError::of)?;
    }
    let img = image::RgbImage::from_raw(width, height, buf)
        .ok_or_else(|| PlotError("plot buffer size".into()))?;
    Ok(super::png_bytes(&img))
}

/// A PNG of panels stacked top to bottom, one per unit (kg, m, m^3 ...), each with its
/// series as lines with points; `title` above. The x axis is time since `since` (a
/// date, shown in the axis label) in hours, days or months as the span needs.
pub fn history_png(
    title: &str,
    since: &str,
    series: &[Series],
    width: u32,
    height: u32,
) -> Result<Vec<u8>, PlotError> {
    let (lo, hi) = series
        .iter()
        .flat_map(|s| &s.points)
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), p| {
            (a.min(p.0), b.max(p.0))
        });
    let (factor, time_unit) = time_axis(hi - lo);
    let series: Vec<Series> = series
        .iter()
        .map(|s| Series {
            name: s.name.clone(),
            unit: s.unit.clone(),
            points: s.points.iter().map(|&(x, y)| (x * factor, y)).collect(),
        })
        .collect();
    let x_desc = format!("{time_unit} since {since}");
    let mut units: Vec<&str> = Vec::new();
    for s in &series {
        if !units.contains(&s.unit.as_str()) {
            units.push(&s.unit);
        }
    }
    drawn_png(title, width, height, |area, text| {
        let panels = area.split_evenly((units.len().max(1), 1));
        for (panel, unit) in panels.iter().zip(&units) {
            let mine: Vec<&Series> = series.iter().filter(|s| &s.unit == unit).collect();
            draw_panel(panel, &mine, (x_desc.as_str(), unit), text)?;
        }
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A machine without the font package still labels its plots: the built-in copy is
    /// taken, plotters accepts it, and text drawn with it puts ink on the image.
    #[test]
    fn without_the_font_package_the_built_in_font_draws_text() {
        let bytes = font_bytes(&["/nonexistent/DejaVuSans.ttf"]);
        assert!(std::ptr::eq(bytes, BUILT_IN_FONT));
        plotters::style::register_font("built-in-test", FontStyle::Normal, bytes)
            .unwrap_or_else(|_| panic!("plotters refused the built-in font"));
        let (w, h) = (200u32, 40u32);
        let mut rgb = vec![255u8; (w * h * 3) as usize];
        {
            let area = BitMapBackend::with_buffer(&mut rgb, (w, h)).into_drawing_area();
            let style = ("built-in-test", 24).into_font().color(&BLACK);
            area.draw_text("girth 1.25 m", &style, (4, 6)).unwrap();
            area.present().unwrap();
        }
        let inked = rgb.chunks(3).filter(|p| p[0] < 128).count();
        assert!(inked > 100, "{inked} dark pixels");
    }

    #[test]
    fn the_time_axis_follows_the_span() {
        assert_eq!(time_axis(0.0), (24.0, "hours"));
        assert_eq!(time_axis(0.3).1, "hours");
        assert_eq!(time_axis(f64::NAN).1, "hours");
        assert_eq!(time_axis(14.0), (1.0, "days"));
        assert_eq!(time_axis(400.0).1, "months");
        // one point, and months of data, both draw
        let one = Series {
            name: "weight".into(),
            unit: "kg".into(),
            points: vec![(0.0, 101.5)],
        };
        assert!(history_png("t", "2026-12-03", &[one], 300, 200).is_ok());
        let year = Series {
            name: "weight".into(),
            unit: "kg".into(),
            points: (0..40).map(|d| (d as f64 * 9.0, 20.0 + d as f64)).collect(),
        };
        assert!(history_png("t", "2026-01-01", &[year], 300, 200).is_ok());
    }
}
