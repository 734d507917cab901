//! Mode histograms: the share of a method's successful rollouts in each behaviour mode, one
//! bar chart per method on a common scale, so a student's lost modes stand beside its
//! teacher's.

use std::path::Path;

use plotters::coord::Shift;
use plotters::prelude::*;

use super::{Figure, grid_shape, palette, save};
use crate::Result;

struct ModeHistograms<'a>(&'a [(String, Vec<f64>)]);

const PANEL: (u32, u32) = (360, 220);

impl Figure for ModeHistograms<'_> {
    fn size(&self) -> (u32, u32) {
        let (r, c) = grid_shape(self.0.len(), 4);
        (PANEL.0 * c as u32, PANEL.1 * r as u32)
    }

    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> Result
    where
        DB::ErrorType: 'static,
    {
        let top = self.0.iter().flat_map(|(_, s)| s.iter().copied()).fold(0.0, f64::max);
        let y1 = if top.is_finite() && top > 0.0 { top * 1.1 } else { 1.0 };
        let (r, c) = grid_shape(self.0.len(), 4);
        for (i, ((method, shares), area)) in
            self.0.iter().zip(root.split_evenly((r, c))).enumerate()
        {
            let reached = shares.iter().filter(|&&s| s > 0.0).count();
            let mut chart = ChartBuilder::on(&area)
                .caption(format!("{method}: {reached}/{} modes", shares.len()), ("sans-serif", 13))
                .margin(6)
                .x_label_area_size(24)
                .y_label_area_size(40)
                .build_cartesian_2d(0.0..shares.len() as f64, 0.0..y1)?;
            chart
                .configure_mesh()
                .x_labels(6)
                .x_label_formatter(&|x| format!("{x:.0}"))
                .y_labels(4)
                .label_style(("sans-serif", 10))
                .draw()?;
            let colour = palette(i).filled();
            chart.draw_series(shares.iter().enumerate().filter(|(_, s)| s.is_finite()).map(
                |(m, &s)| Rectangle::new([(m as f64 + 0.1, 0.0), (m as f64 + 0.9, s)], colour),
            ))?;
        }
        Ok(())
    }
}

/// Writes the mode-histogram figure `stem.svg` (and `stem.png`): for each `(method, shares)`,
/// the share of its successful rollouts in each mode (mode index on the x axis), four charts a
/// row, one y scale for all. Writes nothing and returns no file without panels. Returns the
/// files written.
///
/// ```
/// use vdd_report::plots::mode_histograms;
/// let stem = std::env::temp_dir().join(format!("vdd-report-doc-modes-{}", std::process::id()));
/// let panels = [("teacher".to_owned(), vec![0.5, 0.5, 0.0]), ("student".into(), vec![1.0, 0.0, 0.0])];
/// assert_eq!(mode_histograms(&stem, &panels, false)?.len(), 1);
/// assert!(mode_histograms(&stem, &[], false)?.is_empty());
/// # std::fs::remove_file(stem.with_extension("svg")).unwrap();
/// # Ok::<(), vdd_report::Error>(())
/// ```
pub fn mode_histograms(
    stem: &Path,
    panels: &[(String, Vec<f64>)],
    png: bool,
) -> Result<Vec<String>> {
    if panels.is_empty() {
        return Ok(Vec::new());
    }
    save(&ModeHistograms(panels), stem, png)
}
