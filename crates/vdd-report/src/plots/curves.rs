//! Learning curves: one small chart per method and series.

use std::path::Path;

use plotters::coord::Shift;
use plotters::prelude::*;

use super::{Curves, Figure, grid_shape, palette, save};
use crate::Result;

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

    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> Result
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

/// Writes the learning-curve figure `stem.svg` (and `stem.png`): one small chart per method
/// and series, five a row; non-finite points are skipped. Writes nothing and returns no file
/// when there is no series. Returns the files written.
///
/// ```
/// use vdd_report::plots::{Curves, learning_curves};
/// let mut curves = Curves::new();
/// curves.insert("loss".into(), vec![(0.0, 1.0), (1.0, 0.5), (2.0, 0.25)]);
/// let stem = std::env::temp_dir().join(format!("vdd-report-doc-curves-{}", std::process::id()));
/// let files = learning_curves(&stem, &[("vdd".into(), curves)], false)?;
/// assert_eq!(files.len(), 1);
/// assert!(learning_curves(&stem, &[], false)?.is_empty());
/// # std::fs::remove_file(stem.with_extension("svg")).unwrap();
/// # Ok::<(), vdd_report::Error>(())
/// ```
pub fn learning_curves(stem: &Path, panels: &[(String, Curves)], png: bool) -> Result<Vec<String>> {
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
