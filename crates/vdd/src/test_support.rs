//! Small analytic teachers for the unit tests.

use faer::{MatMut, MatRef};
use vdd_core::{CoreError, ScoreModel, check_score_args, gaussian};

/// An isotropic Gaussian mixture in `d` dimensions (state ignored), exact at every σ.
#[derive(Debug, Clone)]
pub struct IsoGmm {
    pub means: Vec<Vec<f32>>,
    pub std: f32,
    pub state_dim: usize,
}

impl IsoGmm {
    pub fn circle(k: usize, radius: f32, std: f32) -> Self {
        let means = (0..k)
            .map(|i| {
                let t = 2.0 * std::f32::consts::PI * i as f32 / k as f32;
                vec![radius * t.cos(), radius * t.sin()]
            })
            .collect();
        Self { means, std, state_dim: 1 }
    }

    pub fn log_density(&self, a: &[f32], sigma: f32) -> f32 {
        let var = self.std * self.std + sigma * sigma;
        let l: Vec<f32> = (0..a.len() * a.len())
            .map(|i| if i % (a.len() + 1) == 0 { var.sqrt() } else { 0.0 })
            .collect();
        let mut w = vec![0.0; a.len()];
        let lw = -(self.means.len() as f32).ln();
        let lps: Vec<f32> =
            self.means.iter().map(|m| lw + gaussian::log_density(a, m, &l, &mut w)).collect();
        gaussian::log_sum_exp(&lps)
    }
}

impl ScoreModel for IsoGmm {
    fn action_dim(&self) -> usize {
        self.means[0].len()
    }
    fn state_dim(&self) -> usize {
        self.state_dim
    }
    fn score(
        &mut self,
        a: MatRef<'_, f32>,
        s: MatRef<'_, f32>,
        sigma: &[f32],
        mut out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        check_score_args(self, a, s, sigma, out.as_ref())?;
        let d = a.ncols();
        let mut lp = vec![0.0; self.means.len()];
        for i in 0..a.nrows() {
            let var = self.std * self.std + sigma[i] * sigma[i];
            for (k, m) in self.means.iter().enumerate() {
                lp[k] = -(0..d).map(|j| (a[(i, j)] - m[j]).powi(2)).sum::<f32>() / (2.0 * var);
            }
            gaussian::softmax_in_place(&mut lp);
            for j in 0..d {
                out[(i, j)] = -(0..self.means.len())
                    .map(|k| lp[k] * (a[(i, j)] - self.means[k][j]))
                    .sum::<f32>()
                    / var;
            }
        }
        Ok(())
    }
    fn sample_actions(
        &mut self,
        states: MatRef<'_, f32>,
        rng: &mut dyn rand::RngCore,
        mut out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        use rand::Rng as _;
        for i in 0..states.nrows() {
            let k = rng.random_range(0..self.means.len());
            for j in 0..out.ncols() {
                out[(i, j)] = self.means[k][j] + self.std * vdd_core::standard_normal(rng);
            }
        }
        Ok(())
    }
}
