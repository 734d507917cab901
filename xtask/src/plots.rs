//! Figures with `plotters`, written as SVG and (optionally) PNG.
//!
//! * [`avoiding_trajectories`]: Avoiding rollouts per method, each step coloured by the expert
//!   the mixture chose (the paper's Figure 4 when the panels are Z = 1, 2, 4, 8);
//! * [`learning_curves`]: training curves per method;
//! * [`toy_density`]: the 2-D toy's density with the teacher's score field and the experts'
//!   2σ ellipses (the paper's Figure 2).
//!
//! `plotters` is built without font support (no `ttf`), so SVG text is left to the viewer and
//! PNGs are drawn through [`PixelFont`], a backend wrapper that renders text with a built-in
//! 5×7 pixel font.

use std::collections::BTreeMap;
use std::path::Path;

use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::FontTransform;
use plotters::style::text_anchor::{HPos, VPos};
use plotters_backend::{
    BackendColor, BackendCoord, BackendStyle, BackendTextStyle, DrawingErrorKind,
};
use serde::{Deserialize, Serialize};
use vdd_tasks::avoiding::rollout::Rollout;
use vdd_tasks::avoiding::{FINISH_Y, OBSTACLES, START};

/// Named training curves: series name → `(x, y)` points.
pub type Curves = BTreeMap<String, Vec<(f64, f64)>>;

type PlotResult<T = ()> = Result<T, Box<dyn std::error::Error>>;

/// A figure that can be drawn on any backend.
trait Figure {
    fn size(&self) -> (u32, u32);
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> PlotResult
    where
        DB::ErrorType: 'static;
}

/// Writes `stem.svg` (and `stem.png`); returns the file names written.
fn save<F: Figure>(fig: &F, stem: &Path, png: bool) -> PlotResult<Vec<String>> {
    if let Some(dir) = stem.parent() {
        std::fs::create_dir_all(dir)?;
    }
    let mut written = Vec::new();
    let svg = stem.with_extension("svg");
    {
        let root = SVGBackend::new(&svg, fig.size()).into_drawing_area();
        root.fill(&WHITE)?;
        fig.draw(&root)?;
        root.present()?;
    }
    written.push(svg.display().to_string());
    if png {
        let path = stem.with_extension("png");
        {
            let root = PixelFont(BitMapBackend::new(&path, fig.size())).into_drawing_area();
            root.fill(&WHITE)?;
            fig.draw(&root)?;
            root.present()?;
        }
        written.push(path.display().to_string());
    }
    Ok(written)
}

/// Distinct colours for experts and series (Tableau 10, then repeated darker).
pub fn palette(i: usize) -> RGBColor {
    const C: [(u8, u8, u8); 10] = [
        (31, 119, 180),
        (255, 127, 14),
        (44, 160, 44),
        (214, 39, 40),
        (148, 103, 189),
        (140, 86, 75),
        (227, 119, 194),
        (127, 127, 127),
        (188, 189, 34),
        (23, 190, 207),
    ];
    let (r, g, b) = C[i % C.len()];
    let k = 1.0 - 0.35 * ((i / C.len()) % 2) as f32;
    RGBColor((r as f32 * k) as u8, (g as f32 * k) as u8, (b as f32 * k) as u8)
}

// ---------------------------------------------------------------------------------------------
// Avoiding trajectories

/// One panel of the trajectory figure.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct TrajectoryPanel {
    /// Method label.
    pub label: String,
    /// End-effector positions per rollout.
    pub paths: Vec<Vec<(f32, f32)>>,
    /// Whether each rollout succeeded.
    pub success: Vec<bool>,
    /// The expert chosen at each step of each rollout, and the number of experts.
    pub experts: Option<(Vec<Vec<usize>>, usize)>,
    /// Success rate and task entropy of the whole evaluation (for the title).
    pub success_rate: f64,
    /// Task entropy.
    pub task_entropy: f64,
}

impl TrajectoryPanel {
    /// The first `n` recorded rollouts of an evaluation.
    pub fn from_rollouts(
        label: &str,
        rollouts: &[Rollout],
        n: usize,
        experts: Option<(Vec<Vec<usize>>, usize)>,
        success_rate: f64,
        task_entropy: f64,
    ) -> Self {
        let mut paths = Vec::new();
        let mut success = Vec::new();
        for r in rollouts.iter().take(n) {
            let Some(tr) = &r.trajectory else { continue };
            let mut p: Vec<(f32, f32)> = (0..tr.observations.nrows())
                .map(|t| (tr.observations[(t, 2)], tr.observations[(t, 3)]))
                .collect();
            p.push((tr.final_observation[2], tr.final_observation[3]));
            paths.push(p);
            success.push(r.success());
        }
        Self { label: label.to_owned(), paths, success, experts, success_rate, task_entropy }
    }
}

struct Trajectories<'a>(&'a [TrajectoryPanel]);

const PANEL: (u32, u32) = (360, 420);

fn grid_shape(n: usize, max_cols: usize) -> (usize, usize) {
    let cols = n.clamp(1, max_cols);
    (n.div_ceil(cols).max(1), cols)
}

impl Figure for Trajectories<'_> {
    fn size(&self) -> (u32, u32) {
        let (r, c) = grid_shape(self.0.len(), 4);
        (PANEL.0 * c as u32, PANEL.1 * r as u32)
    }

    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> PlotResult
    where
        DB::ErrorType: 'static,
    {
        let (r, c) = grid_shape(self.0.len(), 4);
        for (panel, area) in self.0.iter().zip(root.split_evenly((r, c))) {
            let title = format!(
                "{}: success {:.2}, entropy {:.2}",
                panel.label, panel.success_rate, panel.task_entropy
            );
            let mut chart = ChartBuilder::on(&area)
                .caption(title, ("sans-serif", 15))
                .margin(8)
                .x_label_area_size(28)
                .y_label_area_size(40)
                .build_cartesian_2d(0.2f32..0.85f32, -0.32f32..0.45f32)?;
            chart
                .configure_mesh()
                .x_labels(5)
                .y_labels(6)
                .light_line_style(WHITE.mix(0.0))
                .label_style(("sans-serif", 11))
                .draw()?;
            // Finish line and obstacles.
            chart.draw_series(LineSeries::new(
                [(0.2f32, FINISH_Y), (0.85, FINISH_Y)],
                ShapeStyle { color: BLACK.mix(0.5), filled: false, stroke_width: 1 },
            ))?;
            for o in OBSTACLES.iter() {
                let pts: Vec<(f32, f32)> = (0..=32)
                    .map(|k| {
                        let a = k as f32 / 32.0 * std::f32::consts::TAU;
                        (o.centre[0] + o.radius * a.cos(), o.centre[1] + o.radius * a.sin())
                    })
                    .collect();
                chart.draw_series(std::iter::once(Polygon::new(pts, BLACK.mix(0.75).filled())))?;
            }
            for (i, path) in panel.paths.iter().enumerate() {
                match &panel.experts {
                    Some((ids, _)) if i < ids.len() && !ids[i].is_empty() => {
                        for (t, w) in path.windows(2).enumerate() {
                            let z = ids[i].get(t).copied().unwrap_or(0);
                            chart.draw_series(LineSeries::new(
                                [w[0], w[1]],
                                ShapeStyle {
                                    color: palette(z).to_rgba(),
                                    filled: false,
                                    stroke_width: 2,
                                },
                            ))?;
                        }
                    }
                    _ => {
                        let color = if panel.success.get(i).copied().unwrap_or(false) {
                            palette(0).mix(0.7)
                        } else {
                            palette(3).mix(0.9)
                        };
                        chart.draw_series(LineSeries::new(
                            path.iter().copied(),
                            ShapeStyle { color, filled: false, stroke_width: 1 },
                        ))?;
                    }
                }
            }
            chart.draw_series(std::iter::once(Circle::new(
                (START[0], START[1]),
                4,
                BLACK.filled(),
            )))?;
            if let Some((_, z)) = &panel.experts {
                // Legend: one coloured square per expert.
                for k in 0..*z {
                    let x = 0.22 + 0.04 * (k % 15) as f32;
                    let y = 0.43 - 0.03 * (k / 15) as f32;
                    chart.draw_series(std::iter::once(Rectangle::new(
                        [(x, y), (x + 0.025, y - 0.02)],
                        palette(k).filled(),
                    )))?;
                }
            }
        }
        Ok(())
    }
}

/// Writes the trajectory figure `stem.svg` / `stem.png`.
pub fn avoiding_trajectories(
    stem: &Path,
    panels: &[TrajectoryPanel],
    png: bool,
) -> PlotResult<Vec<String>> {
    save(&Trajectories(panels), stem, png)
}

// ---------------------------------------------------------------------------------------------
// Learning curves

/// One small chart of the learning-curve figure.
struct CurveChart<'a> {
    method: &'a str,
    series: &'a str,
    points: &'a [(f64, f64)],
}

struct LearningCurves<'a>(Vec<CurveChart<'a>>);

const CURVE: (u32, u32) = (330, 240);

impl Figure for LearningCurves<'_> {
    fn size(&self) -> (u32, u32) {
        let (r, c) = grid_shape(self.0.len(), 5);
        (CURVE.0 * c as u32, CURVE.1 * r as u32)
    }

    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> PlotResult
    where
        DB::ErrorType: 'static,
    {
        let (r, c) = grid_shape(self.0.len(), 5);
        for (i, (chart, area)) in self.0.iter().zip(root.split_evenly((r, c))).enumerate() {
            let CurveChart { method, series, points } = chart;
            let finite: Vec<(f64, f64)> =
                points.iter().copied().filter(|p| p.0.is_finite() && p.1.is_finite()).collect();
            if finite.is_empty() {
                continue;
            }
            let (x0, x1) = bounds(finite.iter().map(|p| p.0));
            let (y0, y1) = bounds(finite.iter().map(|p| p.1));
            let mut chart = ChartBuilder::on(&area)
                .caption(format!("{method}: {series}"), ("sans-serif", 13))
                .margin(6)
                .x_label_area_size(24)
                .y_label_area_size(48)
                .build_cartesian_2d(x0..x1, y0..y1)?;
            chart
                .configure_mesh()
                .x_labels(4)
                .y_labels(5)
                .label_style(("sans-serif", 10))
                .draw()?;
            chart.draw_series(LineSeries::new(
                finite,
                ShapeStyle { color: palette(i).to_rgba(), filled: false, stroke_width: 2 },
            ))?;
        }
        Ok(())
    }
}

/// A padded `[min, max]` of finite values.
fn bounds(xs: impl Iterator<Item = f64>) -> (f64, f64) {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for x in xs {
        lo = lo.min(x);
        hi = hi.max(x);
    }
    if !lo.is_finite() {
        return (0.0, 1.0);
    }
    let pad = ((hi - lo) * 0.05).max(1e-9 + lo.abs() * 1e-6);
    (lo - pad, hi + pad)
}

/// Writes the learning-curve figure (one small chart per method and series).
pub fn learning_curves(
    stem: &Path,
    panels: &[(String, Curves)],
    png: bool,
) -> PlotResult<Vec<String>> {
    let mut charts = Vec::new();
    for (method, curves) in panels {
        for (series, pts) in curves {
            charts.push(CurveChart { method, series, points: pts });
        }
    }
    if charts.is_empty() {
        return Ok(Vec::new());
    }
    save(&LearningCurves(charts), stem, png)
}

// ---------------------------------------------------------------------------------------------
// Toy density, score field and experts

/// One panel of the toy figure, in raw action coordinates.
#[derive(Debug, Clone)]
pub struct DensityPanel {
    /// Title.
    pub title: String,
    /// Plotted square `[-extent, extent]²`.
    pub extent: f32,
    /// Density values on an `n x n` grid of cell centres, row `i` at `y_i`, column `j` at `x_j`
    /// (row-major, `y` increasing).
    pub density: Vec<f32>,
    /// Grid size `n`.
    pub n: usize,
    /// Score arrows: `(position, direction)` with the direction already scaled for display.
    pub arrows: Vec<((f32, f32), (f32, f32))>,
    /// The experts at the panel's state.
    pub experts: Vec<ExpertEllipse>,
    /// Target modes.
    pub modes: Vec<(f32, f32)>,
}

/// One expert of a [`DensityPanel`], in raw action coordinates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ExpertEllipse {
    /// Mean `(x, y)`.
    pub mean: (f32, f32),
    /// Covariance `[[a, b], [b, c]]` as `(a, b, c)`.
    pub cov: (f32, f32, f32),
    /// Gating weight `q(z|s)`.
    pub weight: f32,
}

struct Density<'a>(&'a [DensityPanel]);

const DENSITY: (u32, u32) = (420, 440);

/// A viridis-like colour map on `[0, 1]`.
pub fn viridis(t: f32) -> RGBColor {
    const STOPS: [(f32, f32, f32); 5] = [
        (68.0, 1.0, 84.0),
        (59.0, 82.0, 139.0),
        (33.0, 145.0, 140.0),
        (94.0, 201.0, 98.0),
        (253.0, 231.0, 37.0),
    ];
    let t = t.clamp(0.0, 1.0) * (STOPS.len() - 1) as f32;
    let i = (t.floor() as usize).min(STOPS.len() - 2);
    let f = t - i as f32;
    let (a, b) = (STOPS[i], STOPS[i + 1]);
    RGBColor(
        (a.0 + f * (b.0 - a.0)) as u8,
        (a.1 + f * (b.1 - a.1)) as u8,
        (a.2 + f * (b.2 - a.2)) as u8,
    )
}

impl Figure for Density<'_> {
    fn size(&self) -> (u32, u32) {
        let (r, c) = grid_shape(self.0.len(), 4);
        (DENSITY.0 * c as u32, DENSITY.1 * r as u32)
    }

    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> PlotResult
    where
        DB::ErrorType: 'static,
    {
        let (r, c) = grid_shape(self.0.len(), 4);
        for (p, area) in self.0.iter().zip(root.split_evenly((r, c))) {
            let e = p.extent;
            let mut chart = ChartBuilder::on(&area)
                .caption(&p.title, ("sans-serif", 14))
                .margin(8)
                .x_label_area_size(26)
                .y_label_area_size(32)
                .build_cartesian_2d(-e..e, -e..e)?;
            chart
                .configure_mesh()
                .disable_mesh()
                .x_labels(5)
                .y_labels(5)
                .label_style(("sans-serif", 10))
                .draw()?;
            let max = p.density.iter().copied().fold(0.0f32, f32::max).max(1e-30);
            let h = 2.0 * e / p.n as f32;
            chart.draw_series((0..p.n * p.n).map(|k| {
                let (i, j) = (k / p.n, k % p.n);
                let (x, y) = (-e + j as f32 * h, -e + i as f32 * h);
                // Square-root scaling keeps low-density regions visible.
                let v = (p.density[k] / max).sqrt();
                Rectangle::new([(x, y), (x + h, y + h)], viridis(v).filled())
            }))?;
            for &((x, y), (dx, dy)) in &p.arrows {
                let style = ShapeStyle { color: WHITE.mix(0.8), filled: false, stroke_width: 1 };
                chart.draw_series(LineSeries::new([(x, y), (x + dx, y + dy)], style))?;
                // Arrow head: two short strokes.
                let (len, ang) = ((dx * dx + dy * dy).sqrt(), dy.atan2(dx));
                for s in [2.6f32, -2.6] {
                    let a = ang + s;
                    let tip = (x + dx, y + dy);
                    chart.draw_series(LineSeries::new(
                        [tip, (tip.0 + 0.35 * len * a.cos(), tip.1 + 0.35 * len * a.sin())],
                        style,
                    ))?;
                }
            }
            for (k, e) in p.experts.iter().enumerate() {
                let ExpertEllipse { mean: (mx, my), cov: (a, b, cc), weight: w } = *e;
                if w < 1e-3 {
                    continue;
                }
                // 2σ ellipse of [[a, b], [b, c]]: eigen-decomposition of the 2x2 covariance.
                let tr = 0.5 * (a + cc);
                let det = (0.25 * (a - cc) * (a - cc) + b * b).sqrt();
                let (l1, l2) = ((tr + det).max(0.0), (tr - det).max(0.0));
                let theta = 0.5 * (2.0 * b).atan2(a - cc);
                let pts: Vec<(f32, f32)> = (0..=48)
                    .map(|i| {
                        let t = i as f32 / 48.0 * std::f32::consts::TAU;
                        let (u, v) = (2.0 * l1.sqrt() * t.cos(), 2.0 * l2.sqrt() * t.sin());
                        (
                            mx + u * theta.cos() - v * theta.sin(),
                            my + u * theta.sin() + v * theta.cos(),
                        )
                    })
                    .collect();
                let width = if w > 0.05 { 2 } else { 1 };
                chart.draw_series(LineSeries::new(
                    pts,
                    ShapeStyle {
                        color: palette(k + 1).to_rgba(),
                        filled: false,
                        stroke_width: width,
                    },
                ))?;
                chart.draw_series(std::iter::once(Cross::new(
                    (mx, my),
                    4,
                    ShapeStyle { color: palette(k + 1).to_rgba(), filled: false, stroke_width: 2 },
                )))?;
            }
            chart
                .draw_series(p.modes.iter().map(|&(x, y)| Circle::new((x, y), 3, RED.filled())))?;
        }
        Ok(())
    }
}

/// Writes the toy figure (density, score field, expert ellipses).
pub fn toy_density(stem: &Path, panels: &[DensityPanel], png: bool) -> PlotResult<Vec<String>> {
    save(&Density(panels), stem, png)
}

// ---------------------------------------------------------------------------------------------
// A bitmap backend that draws text with a built-in pixel font

/// Wraps a drawing backend and renders text with a built-in 5×7 pixel font (scaled with the
/// font size), so raster figures get titles and labels without system fonts.
pub struct PixelFont<B>(pub B);

/// Pixel scale of a glyph for a font size.
fn glyph_scale(size: f64) -> i32 {
    ((size / 11.0).round() as i32).max(1)
}

/// Width and height in pixels of `text` at scale `s` (6·s per character, 7·s tall).
fn text_box(text: &str, s: i32) -> (i32, i32) {
    let n = text.chars().count() as i32;
    ((6 * n - 1).max(0) * s, 7 * s)
}

fn glyph(c: char) -> [u8; 7] {
    GLYPHS
        .iter()
        .find(|(g, _)| *g == c)
        .map(|(_, b)| *b)
        .unwrap_or([0x1f, 0x11, 0x11, 0x11, 0x11, 0x11, 0x1f])
}

impl<B: DrawingBackend> DrawingBackend for PixelFont<B> {
    type ErrorType = B::ErrorType;

    fn get_size(&self) -> (u32, u32) {
        self.0.get_size()
    }
    fn ensure_prepared(&mut self) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.0.ensure_prepared()
    }
    fn present(&mut self) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.0.present()
    }
    fn draw_pixel(
        &mut self,
        point: BackendCoord,
        color: BackendColor,
    ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.0.draw_pixel(point, color)
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
        upper_left: BackendCoord,
        bottom_right: BackendCoord,
        style: &S,
        fill: bool,
    ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.0.draw_rect(upper_left, bottom_right, style, fill)
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
        center: BackendCoord,
        radius: u32,
        style: &S,
        fill: bool,
    ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.0.draw_circle(center, radius, style, fill)
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

    fn draw_text<TStyle: BackendTextStyle>(
        &mut self,
        text: &str,
        style: &TStyle,
        pos: BackendCoord,
    ) -> Result<(), DrawingErrorKind<Self::ErrorType>> {
        let color = style.color();
        if color.alpha == 0.0 {
            return Ok(());
        }
        let s = glyph_scale(style.size());
        let (w, h) = text_box(text, s);
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
        let trans: FontTransform = style.transform();
        let (sw, sh) = self.0.get_size();
        for (k, c) in text.chars().enumerate() {
            let rows = glyph(c);
            for (r, bits) in rows.iter().enumerate() {
                for col in 0..5 {
                    if bits & (1 << (4 - col)) == 0 {
                        continue;
                    }
                    for u in 0..s {
                        for v in 0..s {
                            let x = (k as i32 * 6 + col) * s + u + dx;
                            let y = r as i32 * s + v + dy;
                            let (x, y) = trans.transform(x, y);
                            let (x, y) = (pos.0 + x, pos.1 + y);
                            if x >= 0 && y >= 0 && x < sw as i32 && y < sh as i32 {
                                self.0.draw_pixel((x, y), color)?;
                            }
                        }
                    }
                }
            }
        }
        Ok(())
    }

    fn estimate_text_size<TStyle: BackendTextStyle>(
        &self,
        text: &str,
        style: &TStyle,
    ) -> Result<(u32, u32), DrawingErrorKind<Self::ErrorType>> {
        let (w, h) = text_box(text, glyph_scale(style.size()));
        Ok((w as u32, h as u32))
    }
}

/// The 5×7 glyphs: one byte per row, bit 4 is the leftmost column.
#[rustfmt::skip]
const GLYPHS: [(char, [u8; 7]); 105] = [
    (' ', [0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x00]),
    ('!', [0x04, 0x04, 0x04, 0x04, 0x04, 0x00, 0x04]),
    ('"', [0x0a, 0x0a, 0x00, 0x00, 0x00, 0x00, 0x00]),
    ('#', [0x0a, 0x0a, 0x1f, 0x0a, 0x1f, 0x0a, 0x0a]),
    ('$', [0x04, 0x0f, 0x14, 0x0e, 0x05, 0x1e, 0x04]),
    ('%', [0x18, 0x19, 0x02, 0x04, 0x08, 0x13, 0x03]),
    ('&', [0x0c, 0x12, 0x14, 0x08, 0x15, 0x12, 0x0d]),
    ('\'', [0x04, 0x04, 0x00, 0x00, 0x00, 0x00, 0x00]),
    ('(', [0x02, 0x04, 0x08, 0x08, 0x08, 0x04, 0x02]),
    (')', [0x08, 0x04, 0x02, 0x02, 0x02, 0x04, 0x08]),
    ('*', [0x00, 0x04, 0x15, 0x0e, 0x15, 0x04, 0x00]),
    ('+', [0x00, 0x04, 0x04, 0x1f, 0x04, 0x04, 0x00]),
    (',', [0x00, 0x00, 0x00, 0x00, 0x0c, 0x04, 0x08]),
    ('-', [0x00, 0x00, 0x00, 0x1f, 0x00, 0x00, 0x00]),
    ('.', [0x00, 0x00, 0x00, 0x00, 0x00, 0x0c, 0x0c]),
    ('/', [0x00, 0x01, 0x02, 0x04, 0x08, 0x10, 0x00]),
    ('0', [0x0e, 0x11, 0x13, 0x15, 0x19, 0x11, 0x0e]),
    ('1', [0x04, 0x0c, 0x04, 0x04, 0x04, 0x04, 0x0e]),
    ('2', [0x0e, 0x11, 0x01, 0x02, 0x04, 0x08, 0x1f]),
    ('3', [0x1f, 0x02, 0x04, 0x02, 0x01, 0x11, 0x0e]),
    ('4', [0x02, 0x06, 0x0a, 0x12, 0x1f, 0x02, 0x02]),
    ('5', [0x1f, 0x10, 0x1e, 0x01, 0x01, 0x11, 0x0e]),
    ('6', [0x06, 0x08, 0x10, 0x1e, 0x11, 0x11, 0x0e]),
    ('7', [0x1f, 0x01, 0x02, 0x04, 0x08, 0x08, 0x08]),
    ('8', [0x0e, 0x11, 0x11, 0x0e, 0x11, 0x11, 0x0e]),
    ('9', [0x0e, 0x11, 0x11, 0x0f, 0x01, 0x02, 0x0c]),
    (':', [0x00, 0x0c, 0x0c, 0x00, 0x0c, 0x0c, 0x00]),
    (';', [0x00, 0x0c, 0x0c, 0x00, 0x0c, 0x04, 0x08]),
    ('<', [0x02, 0x04, 0x08, 0x10, 0x08, 0x04, 0x02]),
    ('=', [0x00, 0x00, 0x1f, 0x00, 0x1f, 0x00, 0x00]),
    ('>', [0x08, 0x04, 0x02, 0x01, 0x02, 0x04, 0x08]),
    ('?', [0x0e, 0x11, 0x01, 0x02, 0x04, 0x00, 0x04]),
    ('@', [0x0e, 0x11, 0x01, 0x0d, 0x15, 0x15, 0x0e]),
    ('A', [0x0e, 0x11, 0x11, 0x1f, 0x11, 0x11, 0x11]),
    ('B', [0x1e, 0x11, 0x11, 0x1e, 0x11, 0x11, 0x1e]),
    ('C', [0x0e, 0x11, 0x10, 0x10, 0x10, 0x11, 0x0e]),
    ('D', [0x1c, 0x12, 0x11, 0x11, 0x11, 0x12, 0x1c]),
    ('E', [0x1f, 0x10, 0x10, 0x1e, 0x10, 0x10, 0x1f]),
    ('F', [0x1f, 0x10, 0x10, 0x1e, 0x10, 0x10, 0x10]),
    ('G', [0x0e, 0x11, 0x10, 0x17, 0x11, 0x11, 0x0f]),
    ('H', [0x11, 0x11, 0x11, 0x1f, 0x11, 0x11, 0x11]),
    ('I', [0x0e, 0x04, 0x04, 0x04, 0x04, 0x04, 0x0e]),
    ('J', [0x07, 0x02, 0x02, 0x02, 0x02, 0x12, 0x0c]),
    ('K', [0x11, 0x12, 0x14, 0x18, 0x14, 0x12, 0x11]),
    ('L', [0x10, 0x10, 0x10, 0x10, 0x10, 0x10, 0x1f]),
    ('M', [0x11, 0x1b, 0x15, 0x15, 0x11, 0x11, 0x11]),
    ('N', [0x11, 0x11, 0x19, 0x15, 0x13, 0x11, 0x11]),
    ('O', [0x0e, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0e]),
    ('P', [0x1e, 0x11, 0x11, 0x1e, 0x10, 0x10, 0x10]),
    ('Q', [0x0e, 0x11, 0x11, 0x11, 0x15, 0x12, 0x0d]),
    ('R', [0x1e, 0x11, 0x11, 0x1e, 0x14, 0x12, 0x11]),
    ('S', [0x0f, 0x10, 0x10, 0x0e, 0x01, 0x01, 0x1e]),
    ('T', [0x1f, 0x04, 0x04, 0x04, 0x04, 0x04, 0x04]),
    ('U', [0x11, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0e]),
    ('V', [0x11, 0x11, 0x11, 0x11, 0x11, 0x0a, 0x04]),
    ('W', [0x11, 0x11, 0x11, 0x15, 0x15, 0x15, 0x0a]),
    ('X', [0x11, 0x11, 0x0a, 0x04, 0x0a, 0x11, 0x11]),
    ('Y', [0x11, 0x11, 0x11, 0x0a, 0x04, 0x04, 0x04]),
    ('Z', [0x1f, 0x01, 0x02, 0x04, 0x08, 0x10, 0x1f]),
    ('[', [0x0e, 0x08, 0x08, 0x08, 0x08, 0x08, 0x0e]),
    ('\\', [0x00, 0x10, 0x08, 0x04, 0x02, 0x01, 0x00]),
    (']', [0x0e, 0x02, 0x02, 0x02, 0x02, 0x02, 0x0e]),
    ('^', [0x04, 0x0a, 0x11, 0x00, 0x00, 0x00, 0x00]),
    ('_', [0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x1f]),
    ('`', [0x08, 0x04, 0x00, 0x00, 0x00, 0x00, 0x00]),
    ('a', [0x00, 0x00, 0x0e, 0x01, 0x0f, 0x11, 0x0f]),
    ('b', [0x10, 0x10, 0x16, 0x19, 0x11, 0x11, 0x1e]),
    ('c', [0x00, 0x00, 0x0e, 0x10, 0x10, 0x11, 0x0e]),
    ('d', [0x01, 0x01, 0x0d, 0x13, 0x11, 0x11, 0x0f]),
    ('e', [0x00, 0x00, 0x0e, 0x11, 0x1f, 0x10, 0x0e]),
    ('f', [0x06, 0x09, 0x08, 0x1c, 0x08, 0x08, 0x08]),
    ('g', [0x00, 0x0f, 0x11, 0x11, 0x0f, 0x01, 0x0e]),
    ('h', [0x10, 0x10, 0x16, 0x19, 0x11, 0x11, 0x11]),
    ('i', [0x04, 0x00, 0x0c, 0x04, 0x04, 0x04, 0x0e]),
    ('j', [0x02, 0x00, 0x06, 0x02, 0x02, 0x12, 0x0c]),
    ('k', [0x10, 0x10, 0x12, 0x14, 0x18, 0x14, 0x12]),
    ('l', [0x0c, 0x04, 0x04, 0x04, 0x04, 0x04, 0x0e]),
    ('m', [0x00, 0x00, 0x1a, 0x15, 0x15, 0x11, 0x11]),
    ('n', [0x00, 0x00, 0x16, 0x19, 0x11, 0x11, 0x11]),
    ('o', [0x00, 0x00, 0x0e, 0x11, 0x11, 0x11, 0x0e]),
    ('p', [0x00, 0x00, 0x1e, 0x11, 0x1e, 0x10, 0x10]),
    ('q', [0x00, 0x00, 0x0d, 0x13, 0x0f, 0x01, 0x01]),
    ('r', [0x00, 0x00, 0x16, 0x19, 0x10, 0x10, 0x10]),
    ('s', [0x00, 0x00, 0x0e, 0x10, 0x0e, 0x01, 0x1e]),
    ('t', [0x08, 0x08, 0x1c, 0x08, 0x08, 0x09, 0x06]),
    ('u', [0x00, 0x00, 0x11, 0x11, 0x11, 0x13, 0x0d]),
    ('v', [0x00, 0x00, 0x11, 0x11, 0x11, 0x0a, 0x04]),
    ('w', [0x00, 0x00, 0x11, 0x11, 0x15, 0x15, 0x0a]),
    ('x', [0x00, 0x00, 0x11, 0x0a, 0x04, 0x0a, 0x11]),
    ('y', [0x00, 0x00, 0x11, 0x11, 0x0f, 0x01, 0x0e]),
    ('z', [0x00, 0x00, 0x1f, 0x02, 0x04, 0x08, 0x1f]),
    ('{', [0x02, 0x04, 0x04, 0x08, 0x04, 0x04, 0x02]),
    ('|', [0x04, 0x04, 0x04, 0x04, 0x04, 0x04, 0x04]),
    ('}', [0x08, 0x04, 0x04, 0x02, 0x04, 0x04, 0x08]),
    ('~', [0x00, 0x00, 0x08, 0x15, 0x02, 0x00, 0x00]),
    ('µ', [0x00, 0x00, 0x11, 0x11, 0x11, 0x1b, 0x14]),
    ('σ', [0x00, 0x00, 0x0f, 0x12, 0x11, 0x11, 0x0e]),
    ('±', [0x04, 0x04, 0x1f, 0x04, 0x04, 0x00, 0x1f]),
    ('×', [0x00, 0x11, 0x0a, 0x04, 0x0a, 0x11, 0x00]),
    ('–', [0x00, 0x00, 0x00, 0x1f, 0x00, 0x00, 0x00]),
    ('≥', [0x08, 0x04, 0x02, 0x04, 0x08, 0x00, 0x1f]),
    ('≤', [0x02, 0x04, 0x08, 0x04, 0x02, 0x00, 0x1f]),
    ('→', [0x00, 0x04, 0x02, 0x1f, 0x02, 0x04, 0x00]),
    ('²', [0x0c, 0x02, 0x04, 0x0e, 0x00, 0x00, 0x00]),
    ('°', [0x0c, 0x12, 0x0c, 0x00, 0x00, 0x00, 0x00]),
];

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn glyphs_are_unique_and_text_boxes_scale() {
        for (i, (c, _)) in GLYPHS.iter().enumerate() {
            assert!(GLYPHS[i + 1..].iter().all(|(d, _)| d != c), "duplicate glyph {c:?}");
        }
        assert_eq!(text_box("ab", 1), (11, 7));
        assert_eq!(text_box("ab", 2), (22, 14));
        assert_eq!(glyph('A'), [0x0e, 0x11, 0x11, 0x1f, 0x11, 0x11, 0x11]);
        assert_eq!(glyph('\u{1}'), [0x1f, 0x11, 0x11, 0x11, 0x11, 0x11, 0x1f], "unknown: a box");
    }

    #[test]
    fn figures_render_to_svg_and_png() {
        let dir = std::env::temp_dir().join(format!("xtask-plots-{}", std::process::id()));
        let panel = TrajectoryPanel {
            label: "vdd-beso".into(),
            paths: vec![vec![(0.525, -0.28), (0.5, 0.0), (0.45, 0.4)]],
            success: vec![true],
            experts: Some((vec![vec![0, 1]], 2)),
            success_rate: 1.0,
            task_entropy: 0.5,
        };
        let files = avoiding_trajectories(&dir.join("traj"), &[panel], true).unwrap();
        assert_eq!(files.len(), 2);
        let svg = std::fs::read_to_string(dir.join("traj.svg")).unwrap();
        assert!(svg.contains("vdd-beso: success 1.00"));
        assert!(std::fs::metadata(dir.join("traj.png")).unwrap().len() > 1000);
        let mut curves = Curves::new();
        curves.insert("loss".into(), vec![(0.0, 1.0), (1.0, 0.5), (2.0, f64::NAN)]);
        assert_eq!(
            learning_curves(&dir.join("curves"), &[("beso".into(), curves)], true).unwrap().len(),
            2
        );
        let d = DensityPanel {
            title: "toy".into(),
            extent: 4.0,
            density: vec![1.0; 16],
            n: 4,
            arrows: vec![((0.0, 0.0), (0.3, 0.1))],
            experts: vec![ExpertEllipse { mean: (1.0, 1.0), cov: (0.25, 0.05, 0.5), weight: 0.5 }],
            modes: vec![(2.0, 0.0)],
        };
        assert_eq!(toy_density(&dir.join("toy"), &[d], true).unwrap().len(), 2);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
