//! Regression tests of issue 36: `--out` must be a new or empty directory or a previous run
//! of the same recipe, checked before anything is written. Before, `--out LINK` with LINK a
//! symlink to `/` exited 0 and wrote six run files into `/`.

use std::path::{Path, PathBuf};

use vdd_lab::Registry;
use vdd_lab::context::check_run_dir;
use vdd_lab::experiment::{Request, run_with};

/// A fresh directory under the system's temporary directory.
fn temp_dir(tag: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("vdd-lab-out-dir-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Runs the toy-gmm recipe (quick) with the project root `root` into `out`.
fn run_into(root: &Path, out: &Path) -> vdd_lab::Result {
    let recipe = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../recipes/toy-gmm.toml");
    let request = Request {
        recipe: recipe.to_str().unwrap().to_owned(),
        overrides: vdd_lab::recipe::Overrides { quick: true, ..Default::default() },
        out: Some(out.to_owned()),
        command: "tests/out_dir.rs".into(),
        root: Some(root.to_owned()),
        ..Default::default()
    };
    run_with(&Registry::builtin(), &request)
}

fn entries(dir: &Path) -> usize {
    std::fs::read_dir(dir).unwrap().count()
}

#[test]
fn a_symlinked_out_is_refused_before_anything_is_written() {
    let root = temp_dir("symlink");
    let target = root.join("target"); // stands for `/`
    std::fs::create_dir_all(&target).unwrap();
    let link = root.join("LINK");
    std::os::unix::fs::symlink(&target, &link).unwrap();
    let e = run_into(&root, &link).unwrap_err().to_string();
    assert!(e.contains(&link.display().to_string()) && e.contains("symbolic link"), "{e}");
    assert_eq!(entries(&target), 0, "nothing written through the link");
    // A symlink to an empty directory or to a previous run is refused as well.
    assert!(check_run_dir(&link, "toy-gmm").is_err());
    std::fs::remove_dir_all(root).unwrap();
}

/// `--out LINK/run` with LINK a symlink to `/` (here a stand-in): the link is a parent of the
/// run directory, which does not exist yet. Before, the check looked at the last component
/// only, found nothing there, and the run was written through the link.
#[test]
fn an_out_through_a_symlinked_parent_is_refused_naming_the_link() {
    let root = temp_dir("parent-link");
    let target = root.join("target"); // stands for `/`
    std::fs::create_dir_all(&target).unwrap();
    let link = root.join("LINK");
    std::os::unix::fs::symlink(&target, &link).unwrap();
    for out in [link.join("run"), link.join("deeper").join("run"), link.join("..").join("run")] {
        let e = run_into(&root, &out).unwrap_err().to_string();
        assert!(e.contains(&link.display().to_string()) && e.contains("symbolic link"), "{e}");
        assert!(e.contains(&out.display().to_string()), "{e}");
        assert_eq!(entries(&target), 0, "nothing written through the link");
    }
    // A trailing slash does not hide the link either.
    let slash = std::path::PathBuf::from(format!("{}/", link.display()));
    assert!(check_run_dir(&slash, "toy-gmm").is_err());
    // Below a real directory, a new run directory is fine.
    assert!(check_run_dir(&target.join("run"), "toy-gmm").is_ok());
    std::fs::remove_dir_all(root).unwrap();
}

#[test]
fn a_foreign_non_empty_directory_or_a_file_is_refused() {
    let root = temp_dir("foreign");
    let out = root.join("mine");
    std::fs::create_dir_all(&out).unwrap();
    std::fs::write(out.join("thesis.tex"), "precious").unwrap();
    let e = run_into(&root, &out).unwrap_err().to_string();
    assert!(e.contains(&out.display().to_string()) && e.contains("not empty"), "{e}");
    assert_eq!(entries(&out), 1);
    // A run of another recipe is foreign too.
    let other = vdd_lab::recipe::run::resolved_header("toy-conditional", "cmd", &out);
    std::fs::write(out.join("resolved.toml"), other + "seeds = [0]\n").unwrap();
    let e = check_run_dir(&out, "toy-gmm").unwrap_err().to_string();
    assert!(e.contains(&out.display().to_string()), "{e}");
    let file = root.join("file");
    std::fs::write(&file, "x").unwrap();
    let e = run_into(&root, &file).unwrap_err().to_string();
    assert!(e.contains(&file.display().to_string()) && e.contains("not a directory"), "{e}");
    std::fs::remove_dir_all(root).unwrap();
}

#[test]
fn a_new_or_empty_directory_and_a_previous_run_of_the_recipe_are_accepted() {
    let root = temp_dir("accepted");
    assert!(check_run_dir(&root.join("new"), "toy-gmm").is_ok());
    let out = root.join("empty");
    std::fs::create_dir_all(&out).unwrap();
    assert!(check_run_dir(&out, "toy-gmm").is_ok());
    let header = vdd_lab::recipe::run::resolved_header("toy-gmm", "cmd", &out);
    std::fs::write(out.join("resolved.toml"), header + "seeds = [0]\n").unwrap();
    std::fs::write(out.join("metrics.json"), "{}").unwrap();
    assert!(check_run_dir(&out, "toy-gmm").is_ok(), "a re-run into its own previous run");
    std::fs::remove_dir_all(root).unwrap();
}
