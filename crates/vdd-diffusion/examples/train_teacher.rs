//! Train a small BESO teacher on a 2-D toy through the `Trainer` interface, save it, load it,
//! sample from it and print the samples as a text figure.
//!
//! ```text
//! cargo run -p vdd-diffusion --example train_teacher [STEPS]
//! ```
//!
//! The toy: 4 Gaussian modes on a circle of radius 2 (std 0.3). A few thousand steps of a
//! 32-wide network take a few seconds and already put samples on every mode; the acceptance
//! checks of `cargo xtask bench teachers` (`vdd_lab::bench::teachers`) tell how close the
//! samples are.

use faer::Mat;
use vdd_core::gmm::Gmm;
use vdd_core::{Policy, Seeds, Trainer};
use vdd_diffusion::metrics::mode_shares;
use vdd_diffusion::{Beso, BesoConfig, NetConfig, TeacherTrainer, TrainConfig};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let steps: u64 = std::env::args().nth(1).map_or(Ok(3000), |s| s.parse())?;

    // 2,000 demonstrations of the toy (state: a constant 0).
    let gmm = Gmm::circle(4, 2.0, 0.3, 0.0)?;
    let means: Vec<Vec<f32>> = (0..gmm.num_components()).map(|k| gmm.mean(k).to_vec()).collect();
    let mut rng = Seeds::new(0).stream("toy-data");
    let states = Mat::<f32>::zeros(2000, 1);
    let mut actions = Mat::<f32>::zeros(2000, 2);
    let mut a = [0.0f32; 2];
    for i in 0..2000 {
        gmm.sample_into(&mut rng, &mut a);
        actions[(i, 0)] = a[0];
        actions[(i, 1)] = a[1];
    }

    // Training, one step at a time, with progress reports.
    let config = BesoConfig {
        net: NetConfig { hidden_dim: 32, num_blocks: 1, ..Default::default() },
        ..Default::default()
    };
    let train = TrainConfig {
        steps,
        batch_size: 256,
        adam: vdd_nn::AdamConfig { lr: 1e-2, ..Default::default() },
        warmup_steps: (steps / 10).min(100),
        ema_decay: 0.98,
        log_every: (steps / 3).max(1),
        ..Default::default()
    };
    let mut trainer = TeacherTrainer::new(&config, &train, states.as_ref(), actions.as_ref(), 0)?;
    let t0 = std::time::Instant::now();
    trainer.run(|report| {
        if let Some(p) = report {
            println!("step {:>5}: loss {:.4}", p.step, p.loss);
        }
    })?;
    let teacher: Beso = trainer.finish()?;
    println!("trained in {:.1} s", t0.elapsed().as_secs_f64());

    // Save and load: the file holds the weights, the configuration and the normalisers.
    let dir = std::env::temp_dir().join(format!("vdd-diffusion-example-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let path = dir.join("teacher.safetensors");
    teacher.save(&path)?;
    let mut loaded = Beso::load(&path, 0)?;
    println!("saved and loaded {}", path.display());

    // Sample as a policy on raw observations (1000 actions at the observation 0).
    loaded.seed(1);
    let mut x = Mat::<f32>::zeros(1000, 2);
    loaded.act_batch(Mat::<f32>::zeros(1000, 1).as_ref(), x.as_mut())?;
    let (min_share, shares) = mode_shares(x.as_ref(), &means);
    println!("share of samples per mode: {shares:.3?} (smallest {min_share:.3})");
    println!("{}", figure(&x, 41, 21, 3.0));
    let one = loaded.act(&[0.0])?;
    println!("one action: [{:+.3}, {:+.3}]", one[0], one[1]);
    std::fs::remove_dir_all(&dir)?;
    Ok(())
}

/// The rows of `x` as a `w x h` character histogram of `[−r, r]²`.
fn figure(x: &Mat<f32>, w: usize, h: usize, r: f32) -> String {
    let mut grid = vec![vec![0usize; w]; h];
    for i in 0..x.nrows() {
        let cx = ((x[(i, 0)] + r) / (2.0 * r) * w as f32).floor();
        let cy = ((r - x[(i, 1)]) / (2.0 * r) * h as f32).floor();
        if (0.0..w as f32).contains(&cx) && (0.0..h as f32).contains(&cy) {
            grid[cy as usize][cx as usize] += 1;
        }
    }
    let shade = [' ', '.', ':', '*', '#'];
    grid.iter()
        .map(|row| row.iter().map(|&c| shade[c.min(shade.len() - 1)]).collect::<String>())
        .collect::<Vec<_>>()
        .join("\n")
}
