//! Small analytic teachers for the unit tests.

use faer::{MatMut, MatRef};
use vdd_core::{
    CoreError, DenoiserForm, Expert, NoiseConvention, ScoreModel, check_score_args, gaussian,
};
use vdd_moe::MoeOutput;

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

/// A one-state, two-expert mixture output from raw rows.
pub fn output<E: Expert>(expert: &E, raws: &[Vec<f32>], log_gating: [f32; 2]) -> MoeOutput {
    let d = expert.action_dim();
    let mut out = MoeOutput {
        n: 1,
        num_experts: 2,
        action_dim: d,
        raw: raws.concat(),
        means: vec![0.0; 2 * d],
        scales: vec![0.0; 2 * d * d],
        log_gating: log_gating.to_vec(),
    };
    for z in 0..2 {
        expert.decode(
            &raws[z],
            &mut out.means[z * d..(z + 1) * d],
            &mut out.scales[z * d * d..(z + 1) * d * d],
        );
    }
    out
}

/// [`IsoGmm`] under a variance-preserving process: at the time `t`, `ᾱ = exp(−t)` and
/// `x = √ᾱ a + √(1 − ᾱ) η`, so `p_t(x) = Σ_k N(x; √ᾱ m_k, (ᾱ std² + 1 − ᾱ) I) / K`.
#[derive(Debug, Clone)]
pub struct VpGmm(pub IsoGmm);

impl VpGmm {
    fn form(t: f32) -> DenoiserForm {
        DenoiserForm::vp((-t).exp())
    }

    /// `log p_t(x)`: the VE density of `x / k` at `σ = √v / k`, less `d ln k`.
    pub fn log_density(&self, x: &[f32], t: f32) -> f32 {
        let f = Self::form(t);
        let y: Vec<f32> = x.iter().map(|v| v / f.scale).collect();
        self.0.log_density(&y, f.variance.sqrt() / f.scale) - x.len() as f32 * f.scale.ln()
    }
}

impl ScoreModel for VpGmm {
    fn action_dim(&self) -> usize {
        self.0.action_dim()
    }
    fn state_dim(&self) -> usize {
        self.0.state_dim
    }
    fn noise_convention(&self) -> NoiseConvention {
        NoiseConvention::Time
    }
    fn denoiser_form(&self, t: f32) -> Option<DenoiserForm> {
        Some(Self::form(t))
    }
    fn sample_actions(
        &mut self,
        states: MatRef<'_, f32>,
        rng: &mut dyn rand::RngCore,
        out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        self.0.sample_actions(states, rng, out)
    }
    fn score(
        &mut self,
        a: MatRef<'_, f32>,
        s: MatRef<'_, f32>,
        t: &[f32],
        mut out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        // score_t(x) = score_VE(x / k, √v / k) / k.
        let (n, d) = (a.nrows(), a.ncols());
        let mut y = faer::Mat::<f32>::zeros(n, d);
        let mut sigma = vec![0.0; n];
        for i in 0..n {
            let f = Self::form(t[i]);
            sigma[i] = f.variance.sqrt() / f.scale;
            for j in 0..d {
                y[(i, j)] = a[(i, j)] / f.scale;
            }
        }
        self.0.score(y.as_ref(), s, &sigma, out.as_mut())?;
        for i in 0..n {
            let k = Self::form(t[i]).scale;
            for j in 0..d {
                out[(i, j)] /= k;
            }
        }
        Ok(())
    }
}
