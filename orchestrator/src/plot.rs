//! Figures with plotters, each written as PNG and SVG: learning curves (median and
//! inter-quartile band), Fig.-6/10-style scatters of per-trial power and efficiency with
//! the fitted line, and Fig.-4-style box plots.
//!
//! Text uses DejaVu Sans shipped inside the `dejavu` crate and registered from bytes
//! (plotters' `ab_glyph` feature), so no system font is needed.
use plotters::coord::Shift;
use plotters::prelude::*;
use std::path::{Path, PathBuf};
use std::sync::Once;

#[derive(Debug, thiserror::Error)]
#[error("cannot draw {path}: {message}")]
pub struct PlotError {
    pub path: PathBuf,
    pub message: String,
}

/// A learning curve: median and quartiles of task % per step.
#[derive(Clone, Debug)]
pub struct Curve {
    pub label: String,
    pub steps: Vec<u64>,
    pub median: Vec<f64>,
    pub q1: Vec<f64>,
    pub q3: Vec<f64>,
}

/// One panel of a scatter figure.
#[derive(Clone, Debug)]
pub struct ScatterPanel {
    pub title: String,
    pub y_label: String,
    /// (x position, value); x positions are 1, 2, … (jittered when drawn).
    pub points: Vec<(f64, f64)>,
    /// (slope, intercept) in x positions.
    pub fit: Option<(f64, f64)>,
    /// Tick labels at the x positions.
    pub ticks: Vec<(f64, String)>,
}

/// Boxes at one x level, one per series (empty samples are skipped).
#[derive(Clone, Debug)]
pub struct BoxGroup {
    pub label: String,
    pub boxes: Vec<Vec<f64>>,
}

const FONT: &str = "sans-serif";
const PALETTE: [RGBColor; 10] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(127, 127, 127),
    RGBColor(188, 189, 34),
    RGBColor(23, 190, 207),
];

fn color(i: usize) -> RGBColor {
    PALETTE[i % PALETTE.len()]
}

fn register_fonts() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        // Both calls only fail on a malformed font file, which the crate does not ship.
        let _ = plotters::style::register_font(FONT, FontStyle::Normal, dejavu::sans::regular());
        let _ = plotters::style::register_font(FONT, FontStyle::Bold, dejavu::sans::bold());
    });
}

type Drawn = Result<(), String>;

mod glyphs {
    use plotters::prelude::{BitMapBackend, DrawingBackend};
    use plotters_backend::{BackendColor, BackendCoord, BackendStyle, BackendTextStyle, DrawingErrorKind, FontStyle};

    /// The bitmap backend with its text drawn by ab_glyph directly. plotters 0.3.7's own
    /// ab_glyph text path drops every glyph's left side bearing, which splits words
    /// ("p ower"); this wrapper places each outline at its pixel bounds and measures text
    /// with the same metrics it draws with. Everything else is delegated.
    pub(super) struct Glyphs<'a>(pub(super) BitMapBackend<'a>);

    fn glyph_fonts() -> &'static [ab_glyph::FontRef<'static>] {
        static FONTS: std::sync::OnceLock<Vec<ab_glyph::FontRef<'static>>> = std::sync::OnceLock::new();
        FONTS.get_or_init(|| {
            [dejavu::sans::regular(), dejavu::sans::bold()]
                .into_iter()
                .filter_map(|b| ab_glyph::FontRef::try_from_slice(b).ok())
                .collect()
        })
    }

    /// Coverage pixels of `text` at `size` px with the top-left of its box at (0, 0), and
    /// the box's width and height.
    fn rasterize(text: &str, size: f64, bold: bool) -> (Vec<(i32, i32, f32)>, u32, u32) {
        use ab_glyph::{Font, ScaleFont};
        let fonts = glyph_fonts();
        let Some(font) = fonts.get(usize::from(bold)).or(fonts.first()) else {
            return (Vec::new(), 0, 0);
        };
        let sf = font.as_scaled(ab_glyph::PxScale::from(size as f32));
        let mut px = Vec::new();
        let mut caret = 0f32;
        let mut prev: Option<ab_glyph::GlyphId> = None;
        for ch in text.chars() {
            let id = sf.glyph_id(ch);
            if let Some(p) = prev {
                caret += sf.kern(p, id);
            }
            let glyph = id.with_scale_and_position(sf.scale(), ab_glyph::point(caret, sf.ascent()));
            caret += sf.h_advance(id);
            prev = Some(id);
            if let Some(outline) = font.outline_glyph(glyph) {
                let b = outline.px_bounds();
                outline.draw(|x, y, c| px.push((b.min.x as i32 + x as i32, b.min.y as i32 + y as i32, c)));
            }
        }
        (px, caret.ceil().max(0.0) as u32, (sf.ascent() - sf.descent()).ceil().max(0.0) as u32)
    }

    impl<'a> DrawingBackend for Glyphs<'a> {
        type ErrorType = <BitMapBackend<'a> as DrawingBackend>::ErrorType;
        fn get_size(&self) -> (u32, u32) {
            self.0.get_size()
        }
        fn ensure_prepared(&mut self) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
            self.0.ensure_prepared()
        }
        fn present(&mut self) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
            self.0.present()
        }
        fn draw_pixel(&mut self, p: BackendCoord, c: BackendColor) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
            self.0.draw_pixel(p, c)
        }
        fn draw_line<S: BackendStyle>(
            &mut self,
            from: BackendCoord,
            to: BackendCoord,
            style: &S,
        ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
            self.0.draw_line(from, to, style)
        }
        fn draw_rect<S: BackendStyle>(
            &mut self,
            a: BackendCoord,
            b: BackendCoord,
            style: &S,
            fill: bool,
        ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
            self.0.draw_rect(a, b, style, fill)
        }
        fn draw_path<S: BackendStyle, I: IntoIterator<Item = BackendCoord>>(
            &mut self,
            path: I,
            style: &S,
        ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
            self.0.draw_path(path, style)
        }
        fn draw_circle<S: BackendStyle>(
            &mut self,
            c: BackendCoord,
            r: u32,
            style: &S,
            fill: bool,
        ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
            self.0.draw_circle(c, r, style, fill)
        }
        fn fill_polygon<S: BackendStyle, I: IntoIterator<Item = BackendCoord>>(
            &mut self,
            vert: I,
            style: &S,
        ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
            self.0.fill_polygon(vert, style)
        }
        fn blit_bitmap(
            &mut self,
            pos: BackendCoord,
            size: (u32, u32),
            src: &[u8],
        ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
            self.0.blit_bitmap(pos, size, src)
        }
        fn estimate_text_size<T: BackendTextStyle>(
            &self,
            text: &str,
            style: &T,
        ) -> Result<(u32, u32), DrawingErrorKind<Self::ErrorType>> {
            let (_, w, h) = rasterize(text, style.size(), matches!(style.style(), FontStyle::Bold));
            Ok((w, h))
        }
        fn draw_text<T: BackendTextStyle>(
            &mut self,
            text: &str,
            style: &T,
            pos: BackendCoord,
        ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
            use plotters_backend::text_anchor::{HPos, VPos};
            let color = style.color();
            if color.alpha == 0.0 {
                return Ok(());
            }
            let (px, w, h) = rasterize(text, style.size(), matches!(style.style(), FontStyle::Bold));
            let (w, h) = (w as i32, h as i32);
            let dx = match style.anchor().h_pos {
                HPos::Left => 0,
                HPos::Right => -w,
                HPos::Center => -w / 2,
            };
            let dy = match style.anchor().v_pos {
                VPos::Top => 0,
                VPos::Center => -h / 2,
                VPos::Bottom => -h,
            };
            let trans = style.transform();
            let (sw, sh) = self.get_size();
            for (x, y, c) in px {
                let (x, y) = trans.transform(x + dx, y + dy);
                let (x, y) = (pos.0 + x, pos.1 + y);
                if x >= 0 && y >= 0 && x < sw as i32 && y < sh as i32 && c > 0.0 {
                    self.0
                        .draw_pixel((x, y), BackendColor { alpha: color.alpha * c.min(1.0) as f64, rgb: color.rgb })?;
                }
            }
            Ok(())
        }
    }
}
use glyphs::Glyphs;

/// Draw with `f` into `<stem>.png` and `<stem>.svg`.
fn both(
    stem: &Path,
    size: (u32, u32),
    f: impl Fn(&DrawingArea<Glyphs, Shift>) -> Drawn,
    g: impl Fn(&DrawingArea<SVGBackend, Shift>) -> Drawn,
) -> Result<Vec<PathBuf>, PlotError> {
    register_fonts();
    let png = stem.with_extension("png");
    let svg = stem.with_extension("svg");
    let err = |path: &Path| {
        let path = path.to_path_buf();
        move |message: String| PlotError { path: path.clone(), message }
    };
    {
        let root = Glyphs(BitMapBackend::new(&png, size)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| e.to_string()).map_err(err(&png))?;
        f(&root).map_err(err(&png))?;
        root.present().map_err(|e| e.to_string()).map_err(err(&png))?;
    }
    {
        let root = SVGBackend::new(&svg, size).into_drawing_area();
        root.fill(&WHITE).map_err(|e| e.to_string()).map_err(err(&svg))?;
        g(&root).map_err(err(&svg))?;
        root.present().map_err(|e| e.to_string()).map_err(err(&svg))?;
    }
    Ok(vec![png, svg])
}

fn s<E: std::fmt::Display>(e: E) -> String {
    e.to_string()
}

/// Task % over time: one median line and IQR band per curve, the threshold dashed.
pub fn learning_curves(stem: &Path, title: &str, curves: &[Curve], threshold: f64) -> Result<Vec<PathBuf>, PlotError> {
    both(stem, (1000, 640), |r| draw_curves(r, title, curves, threshold), |r| draw_curves(r, title, curves, threshold))
}

fn draw_curves<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    title: &str,
    curves: &[Curve],
    threshold: f64,
) -> Drawn {
    let t_max = curves.iter().filter_map(|c| c.steps.last()).copied().max().unwrap_or(1).max(1);
    let mut chart = ChartBuilder::on(root)
        .caption(title, (FONT, 20))
        .margin(15)
        .x_label_area_size(45)
        .y_label_area_size(60)
        .margin_right(40)
        .build_cartesian_2d(0f64..t_max as f64, 0f64..100f64)
        .map_err(s)?;
    chart
        .configure_mesh()
        .x_label_formatter(&|v| format!("{v:.0}"))
        .y_label_formatter(&|v| format!("{v:.0}"))
        .x_desc("step")
        .y_desc("task %")
        .label_style((FONT, 14))
        .axis_desc_style((FONT, 16))
        .light_line_style(WHITE.mix(0.0))
        .draw()
        .map_err(s)?;
    chart
        .draw_series(DashedLineSeries::new(
            [(0.0, threshold), (t_max as f64, threshold)],
            6,
            4,
            BLACK.mix(0.4).stroke_width(1),
        ))
        .map_err(s)?;
    for (i, c) in curves.iter().enumerate() {
        let col = color(i);
        let mut band: Vec<(f64, f64)> = c.steps.iter().zip(&c.q3).map(|(&x, &y)| (x as f64, y)).collect();
        band.extend(c.steps.iter().zip(&c.q1).rev().map(|(&x, &y)| (x as f64, y)));
        chart.draw_series(std::iter::once(Polygon::new(band, col.mix(0.18).filled()))).map_err(s)?;
        chart
            .draw_series(LineSeries::new(
                c.steps.iter().zip(&c.median).map(|(&x, &y)| (x as f64, y)),
                col.stroke_width(2),
            ))
            .map_err(s)?
            .label(c.label.clone())
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], col.stroke_width(3)));
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::LowerRight)
        .label_font((FONT, 14))
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK.mix(0.5))
        .draw()
        .map_err(s)?;
    Ok(())
}

/// Per-trial points against x position, with the least-squares line, one panel each.
pub fn scatter(stem: &Path, title: &str, panels: &[ScatterPanel], x_label: &str) -> Result<Vec<PathBuf>, PlotError> {
    let w = 560 * panels.len().max(1) as u32;
    both(stem, (w, 560), |r| draw_scatter(r, title, panels, x_label), |r| draw_scatter(r, title, panels, x_label))
}

/// Deterministic horizontal jitter in [−0.15, 0.15] for the i-th point.
fn jitter(i: usize) -> f64 {
    ((i as f64 * 0.618_033_988_75).fract() - 0.5) * 0.3
}

fn tick_label(ticks: &[(f64, String)], x: f64) -> String {
    ticks.iter().find(|(p, _)| (p - x).abs() < 1e-6).map(|(_, l)| l.clone()).unwrap_or_default()
}

fn draw_scatter<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    title: &str,
    panels: &[ScatterPanel],
    x_label: &str,
) -> Drawn {
    let root = root.titled(title, (FONT, 20)).map_err(s)?;
    let areas = root.split_evenly((1, panels.len().max(1)));
    for (p, area) in panels.iter().zip(areas) {
        let k = p.ticks.len().max(1) as f64;
        let (lo, hi) = p.points.iter().fold((0f64, 100f64), |(lo, hi), &(_, y)| (lo.min(y), hi.max(y)));
        let pad = (hi - lo) * 0.05;
        let mut chart = ChartBuilder::on(&area)
            .caption(&p.title, (FONT, 16))
            .margin(12)
            .x_label_area_size(45)
            .y_label_area_size(55)
            .build_cartesian_2d(0.5f64..k + 0.5, (lo - pad)..(hi + pad))
            .map_err(s)?;
        let fmt = |x: &f64| tick_label(&p.ticks, *x);
        chart
            .configure_mesh()
            .x_labels(p.ticks.len() * 2 + 1)
            .x_label_formatter(&fmt)
            .y_label_formatter(&|v| format!("{v:.0}"))
            .x_desc(x_label)
            .y_desc(&p.y_label)
            .label_style((FONT, 13))
            .axis_desc_style((FONT, 15))
            .light_line_style(WHITE.mix(0.0))
            .draw()
            .map_err(s)?;
        chart
            .draw_series(
                p.points
                    .iter()
                    .enumerate()
                    .map(|(i, &(x, y))| Circle::new((x + jitter(i), y), 3, color(0).mix(0.55).filled())),
            )
            .map_err(s)?;
        if let Some((m, b)) = p.fit {
            chart
                .draw_series(LineSeries::new(
                    [(0.5, m * 0.5 + b), (k + 0.5, m * (k + 0.5) + b)],
                    color(3).stroke_width(2),
                ))
                .map_err(s)?;
        }
    }
    Ok(())
}

/// Box plots (Matplotlib style: box = quartiles, line = median, whiskers to the
/// farthest point within 1.5 IQR, points beyond drawn as fliers).
pub fn boxes(
    stem: &Path,
    title: &str,
    groups: &[BoxGroup],
    series: &[String],
    x_label: &str,
) -> Result<Vec<PathBuf>, PlotError> {
    let w = (200 + 90 * groups.len() * series.len().max(1)).clamp(700, 1600) as u32;
    both(
        stem,
        (w, 560),
        |r| draw_boxes(r, title, groups, series, x_label),
        |r| draw_boxes(r, title, groups, series, x_label),
    )
}

fn draw_boxes<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    title: &str,
    groups: &[BoxGroup],
    series: &[String],
    x_label: &str,
) -> Drawn {
    let k = groups.len().max(1) as f64;
    let ticks: Vec<(f64, String)> = groups.iter().enumerate().map(|(i, g)| (i as f64 + 1.0, g.label.clone())).collect();
    let mut chart = ChartBuilder::on(root)
        .caption(title, (FONT, 20))
        .margin(15)
        .x_label_area_size(45)
        .y_label_area_size(60)
        .build_cartesian_2d(0.5f64..k + 0.5, 0f64..100f64)
        .map_err(s)?;
    let fmt = |x: &f64| tick_label(&ticks, *x);
    chart
        .configure_mesh()
        .x_labels(groups.len() * 2 + 1)
        .x_label_formatter(&fmt)
        .y_label_formatter(&|v| format!("{v:.0}"))
        .x_desc(x_label)
        .y_desc("final task %")
        .label_style((FONT, 14))
        .axis_desc_style((FONT, 16))
        .light_line_style(WHITE.mix(0.0))
        .draw()
        .map_err(s)?;
    let ns = series.len().max(1);
    let width = 0.8 / ns as f64;
    for (si, series_label) in series.iter().enumerate().take(ns) {
        let col = color(si);
        let mut first = true;
        for (gi, g) in groups.iter().enumerate() {
            let Some(vals) = g.boxes.get(si) else {
                continue;
            };
            let mut v = vals.clone();
            v.sort_by(|a, b| a.total_cmp(b));
            let (Some(q1), Some(med), Some(q3)) = (
                crate::metrics::quantile(&v, 0.25),
                crate::metrics::quantile(&v, 0.5),
                crate::metrics::quantile(&v, 0.75),
            ) else {
                continue;
            };
            let iqr = q3 - q1;
            let lo = v.iter().copied().find(|&x| x >= q1 - 1.5 * iqr).unwrap_or(q1);
            let hi = v.iter().rev().copied().find(|&x| x <= q3 + 1.5 * iqr).unwrap_or(q3);
            let c = gi as f64 + 1.0 + (si as f64 - (ns as f64 - 1.0) / 2.0) * width;
            let half = width * 0.4;
            let series_box = chart
                .draw_series([
                    Rectangle::new([(c - half, q1), (c + half, q3)], col.mix(0.35).filled()),
                    Rectangle::new([(c - half, q1), (c + half, q3)], col.stroke_width(1)),
                ])
                .map_err(s)?;
            if first && !series_label.is_empty() {
                series_box
                    .label(series_label.clone())
                    .legend(move |(x, y)| Rectangle::new([(x, y - 5), (x + 14, y + 5)], col.mix(0.6).filled()));
            }
            first = false;
            chart
                .draw_series([
                    PathElement::new(vec![(c - half, med), (c + half, med)], BLACK.stroke_width(2)),
                    PathElement::new(vec![(c, q3), (c, hi)], col.stroke_width(1)),
                    PathElement::new(vec![(c, q1), (c, lo)], col.stroke_width(1)),
                    PathElement::new(vec![(c - half / 2.0, hi), (c + half / 2.0, hi)], col.stroke_width(1)),
                    PathElement::new(vec![(c - half / 2.0, lo), (c + half / 2.0, lo)], col.stroke_width(1)),
                ])
                .map_err(s)?;
            chart
                .draw_series(
                    v.iter().filter(|&&x| x < lo || x > hi).map(|&x| Circle::new((c, x), 3, col.stroke_width(1))),
                )
                .map_err(s)?;
        }
    }
    if series.iter().any(|l| !l.is_empty()) {
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::LowerRight)
            .label_font((FONT, 14))
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK.mix(0.5))
            .draw()
            .map_err(s)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn jitter_is_bounded_and_deterministic() {
        for i in 0..1000 {
            assert!(jitter(i).abs() <= 0.15);
            assert_eq!(jitter(i), jitter(i));
        }
    }
}
