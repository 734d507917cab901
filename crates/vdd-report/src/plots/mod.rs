//! Figures with `plotters`, written as SVG and (optionally) PNG.
//!
//! * [`trajectories`]: 2-D paths per method in a fixed [`Scene`] (obstacles, a finish line, a
//!   start), each step coloured by the expert that acted (the paper's Figure 4 for Avoiding when
//!   the panels are Z = 1, 2, 4, 8);
//! * [`learning_curves`]: training curves per method;
//! * [`mode_histograms`]: the share of successful rollouts per behaviour mode, per method;
//! * [`density`]: a 2-D density with a score field and experts' 2σ ellipses (the paper's
//!   Figure 2 for the toy mixtures).
//!
//! Every function takes plain data and writes `stem.svg` (and `stem.png` when asked),
//! returning the paths written. `plotters` is built without font support (no `ttf`), so SVG
//! text is left to the viewer and PNGs are drawn through [`PixelFont`], a backend wrapper that
//! renders text with a built-in 5×7 pixel font.

use std::collections::BTreeMap;
use std::path::Path;

use plotters::coord::Shift;
use plotters::prelude::*;

use crate::{Error, Result};

mod curves;
mod density;
mod modes;
mod pixel_font;
mod trajectories;

pub use curves::learning_curves;
pub use density::{DensityPanel, ExpertEllipse, density, viridis};
pub use modes::mode_histograms;
pub use pixel_font::PixelFont;
pub use trajectories::{Disc, Scene, TrajectoryPanel, Zone, trajectories};

/// Named training curves: series name → `(x, y)` points.
pub type Curves = BTreeMap<String, Vec<(f64, f64)>>;

/// A figure that can be drawn on any backend.
trait Figure {
    fn size(&self) -> (u32, u32);
    fn draw<DB: DrawingBackend>(&self, root: &DrawingArea<DB, Shift>) -> Result
    where
        DB::ErrorType: 'static;
}

/// Writes `stem.svg` (and `stem.png`); returns the file names written.
fn save<F: Figure>(fig: &F, stem: &Path, png: bool) -> Result<Vec<String>> {
    if let Some(dir) = stem.parent() {
        std::fs::create_dir_all(dir)
            .map_err(|source| Error::CreateDir { path: dir.to_path_buf(), source })?;
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
///
/// ```
/// use vdd_report::plots::palette;
/// assert_eq!(palette(0), plotters::style::RGBColor(31, 119, 180));
/// assert_ne!(palette(10), palette(0));
/// ```
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

/// Rows and columns of a grid of `n` panels with at most `max_cols` columns.
fn grid_shape(n: usize, max_cols: usize) -> (usize, usize) {
    let cols = n.clamp(1, max_cols);
    (n.div_ceil(cols).max(1), cols)
}

#[cfg(test)]
mod tests;
