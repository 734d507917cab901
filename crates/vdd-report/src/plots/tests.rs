use super::*;

fn scene() -> Scene {
    Scene {
        x_range: (0.2, 0.85),
        y_range: (-0.32, 0.45),
        finish_y: Some(0.35),
        obstacles: vec![Disc { centre: (0.5, -0.1), radius: 0.03 }],
        zones: vec![],
        start: Some((0.525, -0.28)),
        legend: (0.22, 0.43),
    }
}

#[test]
fn figures_render_to_svg_and_png() {
    let dir = std::env::temp_dir().join(format!("vdd-report-plots-{}", std::process::id()));
    let panel = TrajectoryPanel {
        label: "vdd-beso".into(),
        paths: vec![vec![(0.525, -0.28), (0.5, 0.0), (0.45, 0.4)]],
        success: vec![true],
        experts: Some((vec![vec![0, 1]], 2)),
        success_rate: 1.0,
        task_entropy: 0.5,
    };
    let plain = TrajectoryPanel { label: "beso".into(), experts: None, ..panel.clone() };
    let files = trajectories(&dir.join("traj"), &scene(), &[panel, plain], true).unwrap();
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
    assert_eq!(density(&dir.join("toy"), &[d], true).unwrap().len(), 2);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn an_unwritable_figure_is_an_error_with_its_source() {
    let file = std::env::temp_dir().join(format!("vdd-report-plots-file-{}", std::process::id()));
    std::fs::write(&file, "not a directory").unwrap();
    let err = learning_curves(
        &file.join("sub").join("curves"),
        &[("m".into(), Curves::from([("loss".into(), vec![(0.0, 1.0)])]))],
        false,
    )
    .unwrap_err();
    assert!(matches!(err, Error::CreateDir { .. }), "{err}");
    assert!(std::error::Error::source(&err).is_some());
    std::fs::remove_file(&file).unwrap();
}

#[test]
fn grids_and_colours() {
    assert_eq!(grid_shape(0, 4), (1, 1));
    assert_eq!(grid_shape(5, 4), (2, 4));
    assert_eq!(viridis(0.0), RGBColor(68, 1, 84));
    assert_eq!(viridis(1.0), RGBColor(253, 231, 37));
}
