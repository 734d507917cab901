//! Distils a teacher of your own into a mixture of experts, and prints what the student does.
//!
//! The teacher is any `vdd::ScoreModel`; here three Gaussian modes around (5, 5) in the
//! environment's units, with their exact score and a sampler. `Vdd::auto`'s plan
//! (`AutoPlan::inspect`) looks at the teacher's samples and picks the student's normalisers,
//! the noise schedule and the experts' starting points; the trainer queries the teacher in its
//! own (raw) units, so the student acts around (5, 5). Only the `vdd` crate is needed.
//!
//! ```text
//! cargo run --release -p vdd --example distil_own_teacher [SEED [ITERATIONS]]
//! ```
//!
//! Every mode holds about a third of the actions (each Gaussian has 96% of its mass within 1.0
//! of its mean). With the paper's toy settings instead (`VddConfig::toy`, `MoeConfig::toy` with
//! six experts and a learned gating), seeds 0 and 1 left one expert between the two lower
//! modes, a local optimum of the reverse KL; `docs/when-vdd-struggles.md` says why.

use vdd::faer::{Mat, MatMut, MatRef};
use vdd::rand::RngCore;
use vdd::{
    ActMode, AutoOptions, AutoPlan, CoreError, DistillData, Policy, ScoreModel, Trainer, Vdd,
};

/// Three equally weighted isotropic Gaussians of standard deviation `std` (state ignored).
struct ThreeModes {
    means: [[f32; 2]; 3],
    std: f32,
}

impl ThreeModes {
    fn around(centre: [f32; 2], radius: f32, std: f32) -> Self {
        let mode = |k: usize| {
            let t = std::f32::consts::FRAC_PI_2 + 2.0 * std::f32::consts::PI * k as f32 / 3.0;
            [centre[0] + radius * t.cos(), centre[1] + radius * t.sin()]
        };
        Self { means: [mode(0), mode(1), mode(2)], std }
    }
}

impl ScoreModel for ThreeModes {
    fn action_dim(&self) -> usize {
        2
    }

    fn state_dim(&self) -> usize {
        1
    }

    /// `∇_a log Σ_k N(a; μ_k, (std² + σ²) I) / 3`.
    fn score(
        &mut self,
        a: MatRef<'_, f32>,
        s: MatRef<'_, f32>,
        sigma: &[f32],
        mut out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        vdd::check_score_args(self, a, s, sigma, out.as_ref())?;
        for i in 0..a.nrows() {
            let var = self.std * self.std + sigma[i] * sigma[i];
            let d2 = |m: &[f32; 2]| (a[(i, 0)] - m[0]).powi(2) + (a[(i, 1)] - m[1]).powi(2);
            let logits = self.means.map(|m| -d2(&m) / (2.0 * var));
            let max = logits.iter().copied().fold(f32::NEG_INFINITY, f32::max);
            let w = logits.map(|l| (l - max).exp());
            let total: f32 = w.iter().sum();
            for j in 0..2 {
                let pull: f32 = (0..3).map(|k| w[k] * (self.means[k][j] - a[(i, j)])).sum();
                out[(i, j)] = pull / (total * var);
            }
        }
        Ok(())
    }

    /// A mode uniformly, then Gaussian noise (the gating step learns from these when the
    /// student's gating is learned and no dataset actions are given).
    fn sample_actions(
        &mut self,
        states: MatRef<'_, f32>,
        rng: &mut dyn RngCore,
        mut out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        for i in 0..states.nrows() {
            let k = (rng.next_u32() % 3) as usize;
            for j in 0..2 {
                out[(i, j)] = self.means[k][j] + self.std * vdd::standard_normal(rng);
            }
        }
        Ok(())
    }
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let centre = [5.0, 5.0];
    let mut teacher = ThreeModes::around(centre, 2.0, 0.4);
    let modes = teacher.means;

    // One seed for the run: the trainer's draws and the student's initialisation.
    let seed = std::env::args().nth(1).map_or(Ok(2), |s| s.parse())?;
    // The run length: picked from the teacher unless given.
    let iterations = std::env::args().nth(2).map(|s| s.parse()).transpose()?;
    // Defaults picked from the teacher: normalisers, noise schedule, and three experts started
    // on a mixture fitted to the teacher's samples (see `vdd::auto`).
    let options = AutoOptions { iterations, ..AutoOptions::new(3, seed) };
    let data = DistillData::from_states(Mat::zeros(32, 1))?; // raw states (one, repeated)
    let plan = AutoPlan::inspect(&mut teacher, &data, &options)?;
    println!("picked: {}", plan.summary());
    let mut vdd = Vdd::from_plan(&plan, teacher, data)?;
    let mut last = None;
    vdd.run(|m| last = Some(*m))?;
    let mut student = vdd.finish()?;
    if let Some(m) = last {
        println!(
            "after {} iterations: expert entropy {:.3} nats, |g| {:.3}",
            m.iteration + 1,
            m.expert.expert_entropy,
            m.expert.corrected_score_rms
        );
    }

    // The figure: 3000 actions of the student, sampled from the mixture, on a grid.
    student.set_act_mode(ActMode { greedy_gating: false, sample_action: true, hold_steps: 0 });
    student.seed(0);
    let (lo, hi, cols, rows) = (1.5f32, 8.5f32, 56usize, 24usize);
    let cell = |x: f32, y: f32| {
        let c = ((x - lo) / (hi - lo) * cols as f32).floor() as usize;
        let r = ((hi - y) / (hi - lo) * rows as f32).floor() as usize;
        (r.min(rows - 1), c.min(cols - 1))
    };
    let mut grid = vec![vec![0u32; cols]; rows];
    let mut near = [0usize; 3];
    let n = 3000;
    for _ in 0..n {
        let a = student.act(&[0.0])?;
        if (lo..hi).contains(&a[0]) && (lo..hi).contains(&a[1]) {
            let (r, c) = cell(a[0], a[1]);
            grid[r][c] += 1;
        }
        for (k, m) in modes.iter().enumerate() {
            if (a[0] - m[0]).hypot(a[1] - m[1]) < 1.0 {
                near[k] += 1;
            }
        }
    }
    let shades = [' ', '.', ':', '-', '=', '+', '*', '#', '%', '@'];
    let max = grid.iter().flatten().copied().max().unwrap_or(1).max(1);
    println!("student's actions on [{lo}, {hi}]² (teacher's modes marked O):");
    let marks: Vec<(usize, usize)> = modes.iter().map(|m| cell(m[0], m[1])).collect();
    for (r, row) in grid.iter().enumerate() {
        let line: String = row
            .iter()
            .enumerate()
            .map(|(c, &count)| {
                if marks.contains(&(r, c)) {
                    'O'
                } else {
                    let level = (count as f32 / max as f32 * 9.0).ceil() as usize;
                    shades[level.min(9)]
                }
            })
            .collect();
        println!("|{line}|");
    }
    for (k, m) in modes.iter().enumerate() {
        println!(
            "mode {k} at ({:.2}, {:.2}): {:.1}% of the actions within 1.0",
            m[0],
            m[1],
            100.0 * near[k] as f64 / n as f64
        );
    }
    Ok(())
}
