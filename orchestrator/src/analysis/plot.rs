//! Figures with plotters, each written as PNG and SVG: learning curves (median and
//! inter-quartile band), Fig.-6/10-style scatters of per-trial power and efficiency with
//! the fitted line, and Fig.-4/8b/9b-style box plots.
//!
//! Tick labels of the level axes are written one word per line (a condition's label
//! `algorithm=geese-bt terms=E+C+F` takes one line per knob), and a figure is made wide
//! enough for its longest line, so long text levels stay readable.
//!
//! Text uses DejaVu Sans shipped inside the `dejavu` crate and registered from bytes
//! (plotters' `ab_glyph` feature), so no system font is needed.
use plotters::coord::types::RangedCoordf64;
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};
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

/// One panel of a scatter figure: per-trial points of one or more series (e.g. the
/// fixed and the stress mutation rule), each with its own fitted line.
#[derive(Clone, Debug)]
pub struct ScatterPanel {
    pub title: String,
    pub x_label: String,
    pub y_label: String,
    pub series: Vec<ScatterSeries>,
    /// Tick labels at the x positions.
    pub ticks: Vec<(f64, String)>,
}

/// The points of one series in a scatter panel.
#[derive(Clone, Debug)]
pub struct ScatterSeries {
    /// Legend text; a panel whose only series has an empty label draws no legend.
    pub label: String,
    /// (x position, value); x positions are 1, 2, … (jittered when drawn).
    pub points: Vec<(f64, f64)>,
    /// (slope, intercept) in x positions.
    pub fit: Option<(f64, f64)>,
}

/// Boxes at one x level, one per series (empty samples are skipped).
#[derive(Clone, Debug)]
pub struct BoxGroup {
    pub label: String,
    pub boxes: Vec<Vec<f64>>,
}

/// The value axis of a box plot.
#[derive(Clone, Debug)]
pub struct BoxAxis {
    pub label: String,
    pub range: (f64, f64),
}

impl BoxAxis {
    /// Final task % on 0–100.
    pub fn task_pct() -> BoxAxis {
        BoxAxis { label: "final task %".into(), range: (0.0, 100.0) }
    }
}

/// A corner of the plot the boxes leave free for the legend: on the right if the
/// rightmost group's values all lie in one half of the range (the other half then is
/// free), else on the left if the leftmost group's do, else upper right.
fn legend_corner(groups: &[BoxGroup], (y0, y1): (f64, f64)) -> SeriesLabelPosition {
    let mid = (y0 + y1) / 2.0;
    // Some(true): every value in the lower half; Some(false): every one in the upper.
    let half = |g: Option<&BoxGroup>| -> Option<bool> {
        let v: Vec<f64> = g?.boxes.iter().flatten().copied().collect();
        if v.is_empty() {
            None
        } else if v.iter().all(|&x| x <= mid) {
            Some(true)
        } else if v.iter().all(|&x| x >= mid) {
            Some(false)
        } else {
            None
        }
    };
    match (half(groups.last()), half(groups.first())) {
        (Some(true), _) => SeriesLabelPosition::UpperRight,
        (Some(false), _) => SeriesLabelPosition::LowerRight,
        (None, Some(true)) => SeriesLabelPosition::UpperLeft,
        (None, Some(false)) => SeriesLabelPosition::LowerLeft,
        (None, None) => SeriesLabelPosition::UpperRight,
    }
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

/// The legend of `chart`'s labelled series, in one style for every figure.
fn legend<'a, DB: DrawingBackend + 'a, CT: CoordTranslate>(
    chart: &mut ChartContext<'a, DB, CT>,
    at: SeriesLabelPosition,
    font: f64,
) -> Drawn {
    chart
        .configure_series_labels()
        .position(at)
        .label_font((FONT, font))
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK.mix(0.5))
        .draw()
        .map_err(s)
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
    learning_curves_marked(stem, title, curves, threshold, &[])
}

/// [`learning_curves`] with a vertical line at each step of `marks` (a perturbation,
/// such as a change of task).
pub fn learning_curves_marked(
    stem: &Path,
    title: &str,
    curves: &[Curve],
    threshold: f64,
    marks: &[u64],
) -> Result<Vec<PathBuf>, PlotError> {
    both(
        stem,
        (1000, 640),
        |r| draw_curves(r, title, curves, threshold, marks),
        |r| draw_curves(r, title, curves, threshold, marks),
    )
}

fn draw_curves<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    title: &str,
    curves: &[Curve],
    threshold: f64,
    marks: &[u64],
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
    for &m in marks {
        chart
            .draw_series(LineSeries::new([(m as f64, 0.0), (m as f64, 100.0)], RED.mix(0.7).stroke_width(2)))
            .map_err(s)?;
    }
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
    legend(&mut chart, SeriesLabelPosition::LowerRight, 14.0)?;
    Ok(())
}

/// Per-trial points against x position, with the least-squares line of each series,
/// in a grid of `columns` panels per row.
pub fn scatter(stem: &Path, title: &str, panels: &[ScatterPanel], columns: usize) -> Result<Vec<PathBuf>, PlotError> {
    let columns = columns.clamp(1, panels.len().max(1));
    let rows = panels.len().div_ceil(columns).max(1);
    let panel_w = panels
        .iter()
        .map(|p| 100 + p.ticks.len().max(1) as u32 * (tick_width(&p.ticks) + 16).max(60))
        .max()
        .unwrap_or(0)
        .clamp(560, 3000);
    let panel_h = 470 + panels.iter().map(|p| x_label_area(&p.ticks)).max().unwrap_or(0);
    let size = (panel_w * columns as u32, 30 + panel_h * rows as u32);
    let grid = (rows, columns);
    both(stem, size, |r| draw_scatter(r, title, panels, grid), |r| draw_scatter(r, title, panels, grid))
}

/// Deterministic horizontal jitter in [−0.15, 0.15] for the i-th point.
fn jitter(i: usize) -> f64 {
    ((i as f64 * 0.618_033_988_75).fract() - 0.5) * 0.3
}

/// Font size of tick labels, and the height of one of their lines.
const TICK_FONT: f64 = 14.0;
const TICK_LINE: i32 = 18;

/// A tick label's lines: one per word.
fn tick_lines(label: &str) -> Vec<&str> {
    label.split_whitespace().collect()
}

/// Width in pixels of the longest tick-label line, estimated before anything is drawn
/// (DejaVu Sans averages about 0.6 em per character).
fn tick_width(ticks: &[(f64, String)]) -> u32 {
    let chars = ticks.iter().flat_map(|(_, l)| tick_lines(l)).map(|l| l.chars().count()).max().unwrap_or(0);
    (chars as f64 * TICK_FONT * 0.62).ceil() as u32
}

/// Height of the x label area: the tick lines, then the axis description.
fn x_label_area(ticks: &[(f64, String)]) -> u32 {
    let lines = ticks.iter().map(|(_, l)| tick_lines(l).len()).max().unwrap_or(1).max(1) as u32;
    14 + lines * TICK_LINE as u32 + 26
}

/// Write the tick labels under the x axis of `chart`, one word per line, centred on
/// their positions (the mesh draws the ticks without text).
fn draw_ticks<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    chart: &ChartContext<DB, Cartesian2d<RangedCoordf64, RangedCoordf64>>,
    ticks: &[(f64, String)],
) -> Drawn {
    let y0 = chart.y_range().start;
    let base = root.get_base_pixel();
    let style = TextStyle::from((FONT, TICK_FONT)).pos(Pos::new(HPos::Center, VPos::Top));
    for (x, label) in ticks {
        let (px, py) = chart.backend_coord(&(*x, y0));
        for (i, line) in tick_lines(label).iter().enumerate() {
            root.draw_text(line, &style, (px - base.0, py - base.1 + 10 + i as i32 * TICK_LINE)).map_err(s)?;
        }
    }
    Ok(())
}

fn draw_scatter<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    title: &str,
    panels: &[ScatterPanel],
    grid: (usize, usize),
) -> Drawn {
    let root = root.titled(title, (FONT, 20)).map_err(s)?;
    let areas = root.split_evenly(grid);
    for (p, area) in panels.iter().zip(areas) {
        let k = p.ticks.len().max(1) as f64;
        let (lo, hi) =
            p.series.iter().flat_map(|c| &c.points).fold((0f64, 100f64), |(lo, hi), &(_, y)| (lo.min(y), hi.max(y)));
        let pad = (hi - lo) * 0.05;
        let mut chart = ChartBuilder::on(&area)
            .caption(&p.title, (FONT, 16))
            .margin(12)
            .x_label_area_size(x_label_area(&p.ticks))
            .y_label_area_size(55)
            .build_cartesian_2d(0.5f64..k + 0.5, (lo - pad)..(hi + pad))
            .map_err(s)?;
        chart
            .configure_mesh()
            .x_labels(p.ticks.len() * 2 + 1)
            .x_label_formatter(&|_| String::new())
            .y_label_formatter(&|v| format!("{v:.0}"))
            .x_desc(&p.x_label)
            .y_desc(&p.y_label)
            .label_style((FONT, 13))
            .axis_desc_style((FONT, 15))
            .light_line_style(WHITE.mix(0.0))
            .draw()
            .map_err(s)?;
        let several = p.series.len() > 1;
        for (si, c) in p.series.iter().enumerate() {
            // One series keeps the look of the paper's figures: blue points, red line.
            let (dots, line) = if several { (color(si), color(si)) } else { (color(0), color(3)) };
            // Series side by side within a level, so that they do not hide each other.
            let shift = if several { (si as f64 - (p.series.len() - 1) as f64 / 2.0) * 0.3 } else { 0.0 };
            let spread = if several { 0.4 } else { 1.0 };
            chart
                .draw_series(
                    c.points.iter().enumerate().map(|(i, &(x, y))| {
                        Circle::new((x + shift + jitter(i) * spread, y), 3, dots.mix(0.55).filled())
                    }),
                )
                .map_err(s)?;
            if let Some((m, b)) = c.fit {
                let drawn = chart
                    .draw_series(LineSeries::new(
                        [(0.5, m * 0.5 + b), (k + 0.5, m * (k + 0.5) + b)],
                        line.stroke_width(2),
                    ))
                    .map_err(s)?;
                if !c.label.is_empty() {
                    drawn
                        .label(&c.label)
                        .legend(move |(x, y)| PathElement::new([(x, y), (x + 18, y)], line.stroke_width(2)));
                }
            }
        }
        if p.series.iter().any(|c| !c.label.is_empty() && c.fit.is_some()) {
            legend(&mut chart, SeriesLabelPosition::LowerLeft, 13.0)?;
        }
        draw_ticks(&area, &chart, &p.ticks)?;
    }
    Ok(())
}

/// Box plots (Matplotlib style: box = quartiles, line = median, whiskers to the
/// farthest point within 1.5 IQR, points beyond drawn as fliers).
/// `series` names the boxes of each group, in order (the legend); `axis` is the value
/// axis.
pub fn boxes(
    stem: &Path,
    title: &str,
    groups: &[BoxGroup],
    series: &[String],
    x_label: &str,
    axis: &BoxAxis,
) -> Result<Vec<PathBuf>, PlotError> {
    let ticks = box_ticks(groups);
    let slot = (90 * series.len().max(1) as u32).max(tick_width(&ticks) + 20);
    let w = (200 + slot * groups.len().max(1) as u32).clamp(700, 4000);
    let h = 500 + x_label_area(&ticks);
    both(
        stem,
        (w, h),
        |r| draw_boxes(r, title, groups, series, x_label, axis),
        |r| draw_boxes(r, title, groups, series, x_label, axis),
    )
}

fn box_ticks(groups: &[BoxGroup]) -> Vec<(f64, String)> {
    groups.iter().enumerate().map(|(i, g)| (i as f64 + 1.0, g.label.clone())).collect()
}

/// Y-axis tick text with as many decimals as the range needs.
fn value_label(v: f64, span: f64) -> String {
    if span >= 20.0 {
        format!("{v:.0}")
    } else if span >= 2.0 {
        format!("{v:.1}")
    } else {
        format!("{v:.3}")
    }
}

fn draw_boxes<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    title: &str,
    groups: &[BoxGroup],
    series: &[String],
    x_label: &str,
    axis: &BoxAxis,
) -> Drawn {
    let k = groups.len().max(1) as f64;
    let ticks = box_ticks(groups);
    let (y0, y1) = axis.range;
    let mut chart = ChartBuilder::on(root)
        .caption(title, (FONT, 20))
        .margin(15)
        .x_label_area_size(x_label_area(&ticks))
        .y_label_area_size(60)
        .build_cartesian_2d(0.5f64..k + 0.5, y0..y1)
        .map_err(s)?;
    chart
        .configure_mesh()
        .x_labels(groups.len() * 2 + 1)
        .x_label_formatter(&|_| String::new())
        .y_label_formatter(&|v| value_label(*v, y1 - y0))
        .x_desc(x_label)
        .y_desc(&axis.label)
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
                crate::analysis::metrics::quantile(&v, 0.25),
                crate::analysis::metrics::quantile(&v, 0.5),
                crate::analysis::metrics::quantile(&v, 0.75),
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
    draw_ticks(root, &chart, &ticks)?;
    if series.iter().any(|l| !l.is_empty()) {
        legend(&mut chart, legend_corner(groups, axis.range), 14.0)?;
    }
    Ok(())
}

/// One panel of a locality map: the agent-steps of one behaviour class per location.
#[derive(Clone, Debug)]
pub struct LocalityPanel {
    pub title: String,
    /// (x, y, agent-steps), every count positive.
    pub points: Vec<(i32, i32, u64)>,
}

/// An object drawn under the points: the box of grid cells it occupies.
#[derive(Clone, Debug)]
pub struct LocalityBox {
    pub label: String,
    /// (x1, y1, x2, y2).
    pub cells: (i32, i32, i32, i32),
    /// Impassable (drawn filled grey).
    pub solid: bool,
}

/// Largest marker radius of a locality map, in pixels.
const LOCALITY_MAX_RADIUS: f64 = 16.0;

/// Marker radius for `count` agent-steps when the largest count of the figure is `max`:
/// the marker's area is proportional to the count (radius ∝ √count, the reference's
/// Matplotlib `s = count`), the largest [`LOCALITY_MAX_RADIUS`] pixels, none below 1.
pub fn locality_radius(count: u64, max: u64) -> i32 {
    let r = LOCALITY_MAX_RADIUS * (count as f64 / max.max(1) as f64).sqrt();
    (r.round() as i32).clamp(1, LOCALITY_MAX_RADIUS as i32)
}

/// The locality map (Fig. 5): one scatter per panel on the same axes, the arena
/// `[-half_w, half_w] × [-half_h, half_h]`, with `boxes` drawn under the points; a last
/// panel overlays every class as the reference's single figure does. Marker sizes share
/// one scale over all panels ([`locality_radius`]).
pub fn locality(
    stem: &Path,
    title: &str,
    panels: &[LocalityPanel],
    (half_w, half_h): (i32, i32),
    boxes: &[LocalityBox],
) -> Result<Vec<PathBuf>, PlotError> {
    let cols = 3u32;
    let rows = (panels.len() as u32 + 1).div_ceil(cols).max(1);
    let side = 440u32;
    let size = (cols * side, rows * (side + 10) + 40);
    let half = (half_w, half_h);
    both(
        stem,
        size,
        |r| draw_locality(r, title, panels, half, boxes, cols, rows),
        |r| draw_locality(r, title, panels, half, boxes, cols, rows),
    )
}

fn draw_locality<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    title: &str,
    panels: &[LocalityPanel],
    (half_w, half_h): (i32, i32),
    boxes: &[LocalityBox],
    cols: u32,
    rows: u32,
) -> Drawn {
    let root = root.titled(title, (FONT, 18)).map_err(s)?;
    let areas = root.split_evenly((rows as usize, cols as usize));
    let max = panels.iter().flat_map(|p| p.points.iter().map(|q| q.2)).max().unwrap_or(1);
    let (xr, yr) = (-f64::from(half_w)..f64::from(half_w), -f64::from(half_h)..f64::from(half_h));
    // Panel i shows class i alone; the one after the last overlays them all.
    for (k, area) in areas.iter().enumerate().take(panels.len() + 1) {
        let overlay = k == panels.len();
        let caption =
            if overlay { "All classes (as the reference's figure)".to_string() } else { panels[k].title.clone() };
        let mut chart = ChartBuilder::on(area)
            .caption(caption, (FONT, 15))
            .margin(8)
            .x_label_area_size(28)
            .y_label_area_size(36)
            .build_cartesian_2d(xr.clone(), yr.clone())
            .map_err(s)?;
        chart
            .configure_mesh()
            .x_labels(5)
            .y_labels(5)
            .x_label_formatter(&|v| format!("{v:.0}"))
            .y_label_formatter(&|v| format!("{v:.0}"))
            .label_style((FONT, 12))
            .light_line_style(WHITE.mix(0.0))
            .bold_line_style(BLACK.mix(0.08))
            .draw()
            .map_err(s)?;
        // The arena's edge (the mesh draws only the left and bottom axes).
        let edge = [(xr.start, yr.start), (xr.end, yr.end)];
        chart.draw_series(std::iter::once(Rectangle::new(edge, BLACK.mix(0.6).stroke_width(1)))).map_err(s)?;
        for b in boxes {
            let (x1, y1, x2, y2) = b.cells;
            let corners = [(f64::from(x1), f64::from(y1)), (f64::from(x2), f64::from(y2))];
            let style = if b.solid { BLACK.mix(0.3).filled() } else { BLACK.mix(0.7).stroke_width(1) };
            chart.draw_series(std::iter::once(Rectangle::new(corners, style))).map_err(s)?;
            let label = Text::new(b.label.clone(), (f64::from(x1), f64::from(y2)), (FONT, 12).into_font());
            chart.draw_series(std::iter::once(label)).map_err(s)?;
        }
        let shown: Vec<usize> = if overlay { (0..panels.len()).collect() } else { vec![k] };
        for i in shown {
            let col = color(i);
            let dots = panels[i].points.iter().map(move |&(x, y, c)| {
                Circle::new((f64::from(x), f64::from(y)), locality_radius(c, max), col.mix(0.5).filled())
            });
            let series = chart.draw_series(dots).map_err(s)?;
            if overlay {
                series
                    .label(panels[i].title.split(" (").next().unwrap_or("").to_string())
                    .legend(move |(x, y)| Circle::new((x + 8, y), 5, col.mix(0.7).filled()));
            }
        }
        if overlay && !panels.is_empty() {
            legend(&mut chart, SeriesLabelPosition::LowerLeft, 12.0)?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn long_tick_labels_widen_the_figure_and_wrap_per_knob() {
        let short = [(1.0, "0.5".to_string()), (2.0, "1".to_string())];
        let long = [(1.0, "algorithm=geese-bt terms=E+C+F".to_string()), (2.0, "algorithm=betr-geese".to_string())];
        assert_eq!(tick_lines(&long[0].1), ["algorithm=geese-bt", "terms=E+C+F"]);
        assert!(tick_width(&long) > 150 && tick_width(&short) < 30);
        assert!(x_label_area(&long) > x_label_area(&short));
        assert_eq!(value_label(0.12345, 1.0), "0.123");
        assert_eq!(value_label(50.0, 100.0), "50");
    }

    #[test]
    fn the_legend_goes_where_the_boxes_are_not() {
        let g = |v: &[f64]| BoxGroup { label: String::new(), boxes: vec![v.to_vec()] };
        let corner = |groups: &[BoxGroup]| legend_corner(groups, (0.0, 100.0));
        assert_eq!(corner(&[g(&[90.0]), g(&[5.0, 20.0])]), SeriesLabelPosition::UpperRight);
        assert_eq!(corner(&[g(&[5.0]), g(&[70.0, 95.0])]), SeriesLabelPosition::LowerRight);
        assert_eq!(corner(&[g(&[60.0, 99.0]), g(&[10.0, 90.0])]), SeriesLabelPosition::LowerLeft);
        assert_eq!(corner(&[g(&[10.0, 90.0]), g(&[10.0, 90.0])]), SeriesLabelPosition::UpperRight);
    }

    #[test]
    fn locality_markers_grow_with_the_square_root_of_the_count() {
        assert_eq!(locality_radius(100, 100), LOCALITY_MAX_RADIUS as i32);
        assert_eq!(locality_radius(25, 100), (LOCALITY_MAX_RADIUS / 2.0) as i32);
        assert_eq!(locality_radius(1, 1_000_000), 1);
        assert_eq!(locality_radius(5, 0), LOCALITY_MAX_RADIUS as i32);
    }

    #[test]
    fn jitter_is_bounded_and_deterministic() {
        for i in 0..1000 {
            assert!(jitter(i).abs() <= 0.15);
            assert_eq!(jitter(i), jitter(i));
        }
    }
}
