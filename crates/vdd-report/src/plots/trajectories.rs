//! Paths in a 2-D scene, coloured by the acting expert.

use std::path::Path;

use plotters::coord::Shift;
use plotters::prelude::*;
use serde::{Deserialize, Serialize};

use super::{Figure, grid_shape, palette, save};
use crate::Result;

/// A disc-shaped obstacle of a [`Scene`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Disc {
    /// Centre `(x, y)`.
    pub centre: (f32, f32),
    /// Radius.
    pub radius: f32,
}

/// An axis-aligned square zone of a [`Scene`] (a target), drawn as a light outline in its
/// palette colour.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Zone {
    /// Centre `(x, y)`.
    pub centre: (f32, f32),
    /// Half the side.
    pub half: f32,
    /// Palette index of its colour ([`super::palette`]).
    pub colour: usize,
}

/// The fixed scene under the paths of a trajectory figure, in the task's coordinates.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Scene {
    /// Plotted `x` interval.
    pub x_range: (f32, f32),
    /// Plotted `y` interval.
    pub y_range: (f32, f32),
    /// A horizontal finish line at this `y`, across the plot.
    pub finish_y: Option<f32>,
    /// Obstacles, drawn as filled dark discs.
    pub obstacles: Vec<Disc>,
    /// Target zones, drawn under the paths.
    #[serde(default)]
    pub zones: Vec<Zone>,
    /// The start position, drawn as a black dot over the paths.
    pub start: Option<(f32, f32)>,
    /// Upper-left corner of the expert legend (one coloured square per expert, 15 a row).
    pub legend: (f32, f32),
}

/// One panel of the trajectory figure.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct TrajectoryPanel {
    /// Method label.
    pub label: String,
    /// Positions `(x, y)` per path (a rollout).
    pub paths: Vec<Vec<(f32, f32)>>,
    /// Whether each path succeeded (its colour when there are no experts).
    pub success: Vec<bool>,
    /// The expert that acted at each step of each path, and the number of experts (the
    /// paths are then coloured step by step, with a legend).
    pub experts: Option<(Vec<Vec<usize>>, usize)>,
    /// Success rate of the whole evaluation (for the title).
    pub success_rate: f64,
    /// Task entropy of the whole evaluation (for the title).
    pub task_entropy: f64,
}

struct Trajectories<'a> {
    scene: &'a Scene,
    panels: &'a [TrajectoryPanel],
}

const PANEL: (u32, u32) = (360, 420);

impl Figure for Trajectories<'_> {
    fn size(&self) -> (u32, u32) {
        let (r, c) = grid_shape(self.panels.len(), 4);
        (PANEL.0 * c as u32, PANEL.1 * r as u32)
    }

    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> Result
    where
        DB::ErrorType: 'static,
    {
        let scene = self.scene;
        let (r, c) = grid_shape(self.panels.len(), 4);
        for (panel, area) in self.panels.iter().zip(root.split_evenly((r, c))) {
            let title = format!(
                "{}: success {:.2}, entropy {:.2}",
                panel.label, panel.success_rate, panel.task_entropy
            );
            let mut chart = ChartBuilder::on(&area)
                .caption(title, ("sans-serif", 15))
                .margin(8)
                .x_label_area_size(28)
                .y_label_area_size(40)
                .build_cartesian_2d(
                    scene.x_range.0..scene.x_range.1,
                    scene.y_range.0..scene.y_range.1,
                )?;
            chart
                .configure_mesh()
                .x_labels(5)
                .y_labels(6)
                .light_line_style(WHITE.mix(0.0))
                .label_style(("sans-serif", 11))
                .draw()?;
            // Finish line and obstacles.
            if let Some(y) = scene.finish_y {
                chart.draw_series(LineSeries::new(
                    [(scene.x_range.0, y), (scene.x_range.1, y)],
                    ShapeStyle { color: BLACK.mix(0.5), filled: false, stroke_width: 1 },
                ))?;
            }
            for o in &scene.obstacles {
                let pts: Vec<(f32, f32)> = (0..=32)
                    .map(|k| {
                        let a = k as f32 / 32.0 * std::f32::consts::TAU;
                        (o.centre.0 + o.radius * a.cos(), o.centre.1 + o.radius * a.sin())
                    })
                    .collect();
                chart.draw_series(std::iter::once(Polygon::new(pts, BLACK.mix(0.75).filled())))?;
            }
            for zone in &scene.zones {
                let (c, h) = (zone.centre, zone.half);
                let corners = [(c.0 - h, c.1 - h), (c.0 + h, c.1 + h)];
                let colour = palette(zone.colour);
                chart.draw_series(std::iter::once(Rectangle::new(
                    corners,
                    colour.mix(0.15).filled(),
                )))?;
                chart.draw_series(std::iter::once(Rectangle::new(
                    corners,
                    colour.stroke_width(2),
                )))?;
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
            if let Some(start) = scene.start {
                chart.draw_series(std::iter::once(Circle::new(start, 4, BLACK.filled())))?;
            }
            if let Some((_, z)) = &panel.experts {
                // Legend: one coloured square per expert.
                for k in 0..*z {
                    let x = scene.legend.0 + 0.04 * (k % 15) as f32;
                    let y = scene.legend.1 - 0.03 * (k / 15) as f32;
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

/// Writes the trajectory figure `stem.svg` (and `stem.png`): one panel per entry of `panels`,
/// four a row, each over `scene`. Returns the files written.
///
/// ```
/// use vdd_report::plots::{Disc, Scene, TrajectoryPanel, trajectories};
/// let scene = Scene {
///     x_range: (0.0, 1.0),
///     y_range: (0.0, 1.0),
///     finish_y: Some(0.9),
///     obstacles: vec![Disc { centre: (0.5, 0.5), radius: 0.05 }],
///     zones: vec![],
///     start: Some((0.5, 0.1)),
///     legend: (0.02, 0.98),
/// };
/// let panel = TrajectoryPanel {
///     label: "mixture".into(),
///     paths: vec![vec![(0.5, 0.1), (0.4, 0.5), (0.45, 0.95)]],
///     success: vec![true],
///     experts: Some((vec![vec![0, 1]], 2)),
///     success_rate: 1.0,
///     task_entropy: 0.0,
/// };
/// let stem = std::env::temp_dir().join(format!("vdd-report-doc-traj-{}", std::process::id()));
/// let files = trajectories(&stem, &scene, &[panel], false)?;
/// assert_eq!(files, [stem.with_extension("svg").display().to_string()]);
/// # std::fs::remove_file(stem.with_extension("svg")).unwrap();
/// # Ok::<(), vdd_report::Error>(())
/// ```
pub fn trajectories(
    stem: &Path,
    scene: &Scene,
    panels: &[TrajectoryPanel],
    png: bool,
) -> Result<Vec<String>> {
    save(&Trajectories { scene, panels }, stem, png)
}
