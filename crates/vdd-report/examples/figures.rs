//! Figures of synthetic data: a two-mode density with its score field and two experts, the
//! learning curve of a made-up run, and two paths around a disc.
//!
//! ```sh
//! cargo run -p vdd-report --example figures -- [OUT_DIR]   # default: a temporary directory
//! ```

use std::path::PathBuf;

use vdd_report::plots::{
    Curves, DensityPanel, Disc, ExpertEllipse, Scene, TrajectoryPanel, density, learning_curves,
    trajectories,
};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let out = std::env::args_os()
        .nth(1)
        .map(PathBuf::from)
        .unwrap_or_else(|| std::env::temp_dir().join("vdd-report-figures"));

    // An equal mixture of two isotropic Gaussians at (±1.5, 0), std 0.5, on a 60 x 60 grid.
    let (n, extent, modes) = (60, 3.0f32, [(-1.5f32, 0.0f32), (1.5, 0.0)]);
    let h = 2.0 * extent / n as f32;
    let pdf = |x: f32, y: f32| -> f32 {
        modes.iter().map(|&(mx, my)| (-((x - mx).powi(2) + (y - my).powi(2)) / 0.5).exp()).sum()
    };
    let centre = |k: usize| -extent + (k as f32 + 0.5) * h;
    let density_values: Vec<f32> = (0..n * n).map(|k| pdf(centre(k % n), centre(k / n))).collect();
    // The score field, scaled for display: towards the nearer mode.
    let mut arrows = Vec::new();
    for i in (0..n).step_by(6) {
        for j in (0..n).step_by(6) {
            let (x, y) = (centre(j), centre(i));
            let m = if x < 0.0 { modes[0] } else { modes[1] };
            arrows.push(((x, y), (0.1 * (m.0 - x), 0.1 * (m.1 - y))));
        }
    }
    let experts = modes
        .iter()
        .map(|&mean| ExpertEllipse { mean, cov: (0.25, 0.0, 0.25), weight: 0.5 })
        .collect();
    let panel = DensityPanel {
        title: "two modes".into(),
        extent,
        density: density_values,
        n,
        arrows,
        experts,
        modes: modes.to_vec(),
    };
    let mut files = density(&out.join("density"), &[panel], true)?;

    let mut curves = Curves::new();
    curves.insert("loss".into(), (0..50).map(|i| (i as f64, (-0.1 * i as f64).exp())).collect());
    files.extend(learning_curves(&out.join("curves"), &[("made-up".into(), curves)], true)?);

    let scene = Scene {
        x_range: (0.0, 1.0),
        y_range: (0.0, 1.0),
        finish_y: Some(0.9),
        obstacles: vec![Disc { centre: (0.5, 0.5), radius: 0.08 }],
        zones: vec![],
        start: Some((0.5, 0.1)),
        legend: (0.03, 0.97),
    };
    let paths = vec![
        vec![(0.5, 0.1), (0.45, 0.3), (0.35, 0.5), (0.45, 0.7), (0.5, 0.95)],
        vec![(0.5, 0.1), (0.55, 0.3), (0.65, 0.5), (0.55, 0.7), (0.5, 0.95)],
    ];
    let panel = TrajectoryPanel {
        label: "two experts".into(),
        paths,
        success: vec![true, true],
        experts: Some((vec![vec![0, 0, 0, 0], vec![1, 1, 1, 1]], 2)),
        success_rate: 1.0,
        task_entropy: 1.0,
    };
    files.extend(trajectories(&out.join("trajectories"), &scene, &[panel], true)?);

    for f in files {
        println!("{f}");
    }
    Ok(())
}
