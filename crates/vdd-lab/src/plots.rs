//! Figures, from `vdd-report`'s plots (see [`vdd_report::plots`]); this module adds what knows
//! the tasks: Avoiding's scene and the panels built from its rollouts, Block-Push's
//! demonstration figure, and Pushing's and Aligning's scenes and mode-coloured panels.

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
        zones: vec![],
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

/// The Block-Push scene for the targets of `targets` (centres; target 0 olive, target 1 cyan,
/// apart from the four modes' colours and the failures'), the workspace window and the
/// effector's start.
pub fn block_push_scene(targets: [[f32; 2]; 2]) -> Scene {
    use vdd_tasks::block_push::{EFFECTOR_START, TARGET_HALF, WORKSPACE};
    Scene {
        x_range: (WORKSPACE[0][0], WORKSPACE[1][0]),
        y_range: (WORKSPACE[0][1], WORKSPACE[1][1]),
        finish_y: None,
        obstacles: vec![],
        zones: (0..2)
            .map(|t| Zone {
                centre: (targets[t][0], targets[t][1]),
                half: TARGET_HALF,
                colour: 8 + t,
            })
            .collect(),
        start: Some((EFFECTOR_START[0], EFFECTOR_START[1])),
        legend: (WORKSPACE[0][0] + 0.01, WORKSPACE[1][1] - 0.02),
    }
}

/// The figure of Block-Push demonstrations (`observations` per episode, `T x 16`, and each
/// episode's mode index): one panel per target layout (the colour coin flip of
/// [`vdd_tasks::block_push::StartState`]), at most `per_panel` episodes each; the effector's
/// path and both blocks' paths are drawn in the colour of the episode's mode (legend: modes
/// `b0→t0, b0→t1, b1→t0, b1→t1`). Returns the files written.
pub fn block_push_demonstrations(
    stem: &Path,
    observations: &[faer::Mat<f32>],
    modes: &[usize],
    per_panel: usize,
    png: bool,
) -> vdd_report::Result<Vec<String>> {
    use vdd_tasks::block_push::N_MODES;
    // Observation columns: block 0 x, y (0, 1), block 1 x, y (4, 5), effector x, y (8, 9),
    // target 0 (12, 13), target 1 (14, 15).
    let path = |o: &faer::Mat<f32>, c: usize| -> Vec<(f32, f32)> {
        (0..o.nrows()).map(|t| (o[(t, c)], o[(t, c + 1)])).collect()
    };
    use vdd_report::plots::TrajectoryPanel as Panel;
    let mut layouts: Vec<([[f32; 2]; 2], Panel)> = Vec::new();
    for (o, &m) in observations.iter().zip(modes).filter(|(o, _)| o.nrows() > 1) {
        let targets = [[o[(0, 12)], o[(0, 13)]], [o[(0, 14)], o[(0, 15)]]];
        let left = usize::from(targets[0][0] > targets[1][0]);
        let at = match layouts.iter().position(|(t, _)| usize::from(t[0][0] > t[1][0]) == left) {
            Some(i) => i,
            None => {
                let label = format!("t0 {}", ["left", "right"][left]);
                let panel = Panel {
                    label,
                    paths: vec![],
                    success: vec![],
                    experts: Some((vec![], N_MODES)),
                    success_rate: 1.0,
                    task_entropy: 0.0,
                };
                layouts.push((targets, panel));
                layouts.len() - 1
            }
        };
        let panel = &mut layouts[at].1;
        if panel.paths.len() >= 3 * per_panel {
            continue;
        }
        for c in [8, 0, 4] {
            let p = path(o, c);
            if let Some((ids, _)) = &mut panel.experts {
                ids.push(vec![m; p.len()]);
            }
            panel.paths.push(p);
            panel.success.push(true);
        }
    }
    let mut files = Vec::new();
    for (k, (targets, mut panel)) in layouts.into_iter().enumerate() {
        let mut counts = [0usize; N_MODES];
        if let Some((ids, _)) = &panel.experts {
            ids.iter()
                .step_by(3)
                .filter_map(|p| p.first())
                .for_each(|&m| counts[m.min(N_MODES - 1)] += 1);
        }
        panel.label = format!("{}, {} demos", panel.label, counts.iter().sum::<usize>());
        panel.task_entropy = f64::from(vdd_tasks::normalized_entropy(&counts));
        let stem = stem.with_file_name(format!(
            "{}-{k}",
            stem.file_name().map_or("block_push".into(), |f| f.to_string_lossy().into_owned())
        ));
        files.extend(trajectories(&stem, &block_push_scene(targets), &[panel], png)?);
    }
    Ok(files)
}

/// One panel of the Block-Push trajectory figure: the effector's paths (observation columns
/// 8–9, then the final observation) of `paths` (`T x 16` observations), each coloured by its
/// episode's mode index (`b0→t0, b0→t1, b1→t0, b1→t1`) or, for a failure, by colour 4.
pub fn block_push_panel(
    label: &str,
    paths: &[PushingPath<'_>],
    success_rate: f64,
    task_entropy: f64,
) -> vdd_report::plots::TrajectoryPanel {
    mode_panel(label, paths, 8, vdd_tasks::block_push::N_MODES, (success_rate, task_entropy))
}

/// Writes the Block-Push trajectory figure `stem.svg` / `stem.png` (one panel per entry) over
/// the scene of `targets` ([`block_push_scene`]).
pub fn block_push_trajectories(
    stem: &Path,
    targets: [[f32; 2]; 2],
    panels: &[vdd_report::plots::TrajectoryPanel],
    png: bool,
) -> vdd_report::Result<Vec<String>> {
    trajectories(stem, &block_push_scene(targets), panels, png)
}

/// The Pushing scene: the two fixed target zones (red, green), the effector's start, the
/// table region around the boxes.
pub fn pushing_scene() -> Scene {
    use vdd_tasks::pushing::{EFFECTOR_START, TARGET_HALF, TARGETS};
    Scene {
        x_range: (0.25, 0.80),
        y_range: (-0.35, 0.5),
        finish_y: None,
        obstacles: vec![],
        // Palette 3 is red, 2 green.
        zones: (0..2)
            .map(|t| Zone {
                centre: (TARGETS[t][0], TARGETS[t][1]),
                half: TARGET_HALF,
                colour: [3, 2][t],
            })
            .collect(),
        start: Some((EFFECTOR_START[0], EFFECTOR_START[1])),
        legend: (0.26, 0.49),
    }
}

/// One path of a Pushing panel: an episode's observations (`T x 12`), its final observation
/// (drawn last, when given) and its mode index (`None`: a failure).
pub type PushingPath<'a> = (&'a faer::Mat<f32>, Option<&'a [f32]>, Option<usize>);

/// One panel of the Pushing trajectory figure: the paths of the pusher (observation columns
/// 2–3, then the final observation) of `paths`, each coloured by its episode's mode index
/// (`Some(0..4)`) or, for an episode without a mode (a failure), by colour 4; the legend
/// shows the four modes (D3IL's `rr→gg, gg→rr, rg→gr, gr→rg`) and the failure colour.
pub fn pushing_panel(
    label: &str,
    paths: &[PushingPath<'_>],
    success_rate: f64,
    task_entropy: f64,
) -> vdd_report::plots::TrajectoryPanel {
    mode_panel(label, paths, 2, vdd_tasks::pushing::N_MODES, (success_rate, task_entropy))
}

/// A panel of the effector's paths (observation columns `x_col`, `x_col + 1`, then the final
/// observation's), each coloured by its mode index (`Some(0..n_modes)`) or by colour `n_modes`
/// (a failure); `(success_rate, task_entropy)` go into its title.
fn mode_panel(
    label: &str,
    paths: &[PushingPath<'_>],
    x_col: usize,
    n_modes: usize,
    (success_rate, task_entropy): (f64, f64),
) -> vdd_report::plots::TrajectoryPanel {
    let mut out = vdd_report::plots::TrajectoryPanel {
        label: label.to_owned(),
        paths: Vec::with_capacity(paths.len()),
        success: Vec::with_capacity(paths.len()),
        experts: Some((Vec::with_capacity(paths.len()), n_modes + 1)),
        success_rate,
        task_entropy,
    };
    for (o, last, mode) in paths {
        let mut p: Vec<(f32, f32)> =
            (0..o.nrows()).map(|t| (o[(t, x_col)], o[(t, x_col + 1)])).collect();
        if let Some(f) = last.filter(|f| f.len() > x_col + 1) {
            p.push((f[x_col], f[x_col + 1]));
        }
        if let Some((ids, _)) = &mut out.experts {
            ids.push(vec![mode.unwrap_or(n_modes).min(n_modes); p.len()]);
        }
        out.paths.push(p);
        out.success.push(mode.is_some());
    }
    out
}

/// The Aligning scene: the effector's start and the region of the tray's starts and targets
/// (the targets are drawn per episode, so no zone is drawn).
pub fn aligning_scene() -> Scene {
    use vdd_tasks::aligning::EFFECTOR_START;
    Scene {
        x_range: (0.25, 0.80),
        y_range: (-0.42, 0.45),
        finish_y: None,
        obstacles: vec![],
        zones: vec![],
        start: Some((EFFECTOR_START[0], EFFECTOR_START[1])),
        legend: (0.26, 0.44),
    }
}

/// One panel of the Aligning trajectory figure: the rod's paths (observation columns 3–4, then
/// the final observation) of `paths` (`T x 14` observations), coloured by mode index (0 inside,
/// 1 outside) or, for a failure, by colour 2.
pub fn aligning_panel(
    label: &str,
    paths: &[PushingPath<'_>],
    success_rate: f64,
    task_entropy: f64,
) -> vdd_report::plots::TrajectoryPanel {
    mode_panel(label, paths, 3, vdd_tasks::aligning::N_MODES, (success_rate, task_entropy))
}

/// Writes the Aligning trajectory figure `stem.svg` / `stem.png` (one panel per entry).
pub fn aligning_trajectories(
    stem: &Path,
    panels: &[vdd_report::plots::TrajectoryPanel],
    png: bool,
) -> vdd_report::Result<Vec<String>> {
    trajectories(stem, &aligning_scene(), panels, png)
}

/// Writes the Pushing trajectory figure `stem.svg` / `stem.png` (one panel per entry).
pub fn pushing_trajectories(
    stem: &Path,
    panels: &[vdd_report::plots::TrajectoryPanel],
    png: bool,
) -> vdd_report::Result<Vec<String>> {
    trajectories(stem, &pushing_scene(), panels, png)
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

    #[test]
    fn the_pushing_figure_colours_paths_by_mode() {
        use vdd_tasks::pushing::oracle::{OracleConfig, generate_demonstrations};
        let demos = generate_demonstrations(2, 2, &OracleConfig::default()).unwrap();
        let paths: Vec<_> = demos
            .observations
            .iter()
            .zip(&demos.modes)
            .map(|(o, m)| (o, None, Some(m.index())))
            .chain(std::iter::once((&demos.observations[0], None, None)))
            .collect();
        let panel = pushing_panel("demos", &paths, 1.0, 0.5);
        let (ids, n) = panel.experts.clone().unwrap();
        assert_eq!(n, 5);
        assert_eq!(ids[2][0], 4);
        assert_eq!(ids[0][0], demos.modes[0].index());
        let dir = std::env::temp_dir().join(format!("vdd-lab-push-fig-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let files = pushing_trajectories(&dir.join("traj"), &[panel], false).unwrap();
        assert_eq!(files.len(), 1);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn the_block_push_rollout_figure_colours_the_effector_by_mode() {
        use vdd_tasks::block_push::oracle::{OracleConfig, generate_demonstrations};
        let demos = generate_demonstrations(2, 3, &OracleConfig::default()).unwrap();
        let o = &demos.observations[0];
        let last: Vec<f32> = (0..o.ncols()).map(|c| o[(0, c)]).collect();
        let paths = [(o, Some(last.as_slice()), Some(demos.modes[0].index())), (o, None, None)];
        let panel = block_push_panel("vdd", &paths, 0.5, 0.25);
        let (ids, n) = panel.experts.clone().unwrap();
        assert_eq!((n, ids[0][0], ids[1][0]), (5, demos.modes[0].index(), 4));
        // The effector's path (columns 8-9) and the final observation appended.
        assert_eq!(panel.paths[0].len(), o.nrows() + 1);
        assert_eq!(panel.paths[1][0], (o[(0, 8)], o[(0, 9)]));
        assert_eq!(panel.success, vec![true, false]);
        let dir = std::env::temp_dir().join(format!("vdd-lab-bp-roll-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let targets = [[o[(0, 12)], o[(0, 13)]], [o[(0, 14)], o[(0, 15)]]];
        let files = block_push_trajectories(&dir.join("traj"), targets, &[panel], false).unwrap();
        assert_eq!(files.len(), 1);
        let svg = std::fs::read_to_string(dir.join("traj.svg")).unwrap();
        assert!(svg.contains("vdd: success 0.50, entropy 0.25"));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn the_block_push_figure_has_a_panel_per_target_layout_and_counts_modes() {
        use vdd_tasks::block_push::oracle::{OracleConfig, generate_demonstrations};
        let demos = generate_demonstrations(6, 2, &OracleConfig::default()).unwrap();
        let modes: Vec<usize> = demos.modes.iter().map(|m| m.index()).collect();
        let layouts = |o: &faer::Mat<f32>| o[(0, 12)] > o[(0, 14)];
        let n_layouts =
            if demos.observations.iter().all(layouts) || !demos.observations.iter().any(layouts) {
                1
            } else {
                2
            };
        let dir = std::env::temp_dir().join(format!("vdd-lab-bp-fig-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let files =
            block_push_demonstrations(&dir.join("traj"), &demos.observations, &modes, 2, false)
                .unwrap();
        assert_eq!(files.len(), n_layouts);
        let svgs: String = files.iter().map(|f| std::fs::read_to_string(f).unwrap()).collect();
        // Each panel's title counts the episodes drawn: at most 2 a panel.
        let counts: Vec<usize> = svgs
            .match_indices(" demos")
            .filter_map(|(i, _)| svgs[..i].rsplit(' ').next()?.parse().ok())
            .collect();
        assert_eq!(counts.len(), n_layouts, "{counts:?}");
        assert!(counts.iter().all(|&c| (1..=2).contains(&c)), "{counts:?}");
        assert!(svgs.contains("t0 left") || svgs.contains("t0 right"));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
