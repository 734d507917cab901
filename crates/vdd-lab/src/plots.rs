//! Figures, from `vdd-report`'s plots (see [`vdd_report::plots`]); this module adds what knows
//! the Avoiding task: its scene and the panels built from its rollouts.

use std::path::Path;

use vdd_tasks::avoiding::rollout::Rollout;
use vdd_tasks::avoiding::{FINISH_Y, OBSTACLES, START};

pub use vdd_report::plots::*;

/// The toy figure (density, score field, expert ellipses).
pub use vdd_report::plots::density as toy_density;

/// The Avoiding scene: obstacles, finish line and start, in the plotted window.
pub fn avoiding_scene() -> Scene {
    Scene {
        x_range: (0.2, 0.85),
        y_range: (-0.32, 0.45),
        finish_y: Some(FINISH_Y),
        obstacles: OBSTACLES
            .iter()
            .map(|o| Disc { centre: (o.centre[0], o.centre[1]), radius: o.radius })
            .collect(),
        start: Some((START[0], START[1])),
        legend: (0.22, 0.43),
    }
}

/// One panel of the Avoiding trajectory figure.
#[derive(Debug, Clone)]
pub struct TrajectoryPanel(pub vdd_report::plots::TrajectoryPanel);

impl TrajectoryPanel {
    /// The end-effector paths of the first `n` recorded rollouts of an evaluation.
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
        Self(vdd_report::plots::TrajectoryPanel {
            label: label.to_owned(),
            paths,
            success,
            experts,
            success_rate,
            task_entropy,
        })
    }
}

/// Writes the Avoiding trajectory figure `stem.svg` / `stem.png`.
pub fn avoiding_trajectories(
    stem: &Path,
    panels: &[TrajectoryPanel],
    png: bool,
) -> vdd_report::Result<Vec<String>> {
    let panels: Vec<_> = panels.iter().map(|p| p.0.clone()).collect();
    trajectories(stem, &avoiding_scene(), &panels, png)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_avoiding_figure_draws_the_task_scene() {
        let scene = avoiding_scene();
        assert_eq!(scene.obstacles.len(), OBSTACLES.len());
        assert_eq!(scene.finish_y, Some(FINISH_Y));
        let dir = std::env::temp_dir().join(format!("xtask-plots-{}", std::process::id()));
        let panel = TrajectoryPanel::from_rollouts("em", &[], 4, None, 0.5, 0.25);
        assert!(panel.0.paths.is_empty());
        let files = avoiding_trajectories(&dir.join("traj"), &[panel], false).unwrap();
        assert_eq!(files.len(), 1);
        let svg = std::fs::read_to_string(dir.join("traj.svg")).unwrap();
        assert!(svg.contains("em: success 0.50, entropy 0.25"));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
