//! A 2-D density with its score field, experts' ellipses and target modes.

use std::path::Path;

use plotters::coord::Shift;
use plotters::prelude::*;

use super::{Figure, grid_shape, palette, save};
use crate::Result;

/// One panel of the density figure, in raw (plotted) coordinates.
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

/// One expert of a [`DensityPanel`], in raw (plotted) coordinates.
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

    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> Result
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

/// Writes the density figure `stem.svg` (and `stem.png`): per panel, the density (square-root
/// colour scale), the score arrows, the experts' 2σ ellipses (weight ≥ 0.001) and the target
/// modes, four panels a row. Returns the files written.
///
/// ```
/// use vdd_report::plots::{DensityPanel, ExpertEllipse, density};
/// let panel = DensityPanel {
///     title: "two modes".into(),
///     extent: 2.0,
///     density: vec![0.1, 0.5, 0.5, 1.0],
///     n: 2,
///     arrows: vec![((0.0, 0.0), (0.2, 0.1))],
///     experts: vec![ExpertEllipse { mean: (1.0, 1.0), cov: (0.2, 0.0, 0.1), weight: 1.0 }],
///     modes: vec![(1.0, 1.0)],
/// };
/// let stem = std::env::temp_dir().join(format!("vdd-report-doc-density-{}", std::process::id()));
/// let files = density(&stem, &[panel], false)?;
/// assert_eq!(files.len(), 1);
/// # std::fs::remove_file(stem.with_extension("svg")).unwrap();
/// # Ok::<(), vdd_report::Error>(())
/// ```
pub fn density(stem: &Path, panels: &[DensityPanel], png: bool) -> Result<Vec<String>> {
    save(&Density(panels), stem, png)
}
