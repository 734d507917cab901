//! **The expert step** (VDD's M-step for the experts; vdd-method.md, "Expert step").
//!
//! Each expert `z` maximises, independently,
//! `J_z(s) = E_{q(a|s,z)}[log π(a|s) + log q̃(z|a,s)] + H[q(a|s,z)]`.
//! With `a = μ_z + L_z ε` and the corrected score
//! `g_z(a,s) = score(a,s,σ) + ∇_a log q̃(z|a,s)`, where
//! `∇_a log q̃(z|a,s) = ∇_a log N(a; μ̃_z, Σ̃_z) − Σ_k q̃(k|a,s) ∇_a log N(a; μ̃_k, Σ̃_k)`
//! is evaluated with the frozen E-step snapshot, the gradients are exactly
//! `∂J_z/∂μ_z = E_ε[g_z]` and `∂J_z/∂L_z = tril(E_ε[g_z εᵀ]) + diag(1/L_z,ii)`.
//!
//! [`corrected_score_moments`] computes `E_ε[g]` and `E_ε[g εᵀ]` for every (state, expert) in
//! one batched teacher call; [`raw_gradients`] turns them into gradients of the experts'
//! raw network outputs through [`Expert::expert_step_grad`].

use faer::{MatMut, MatRef};
use rand::RngCore;
use vdd_core::gaussian;
use vdd_core::{CoreError, Expert, NoiseSchedule, ScoreModel};
use vdd_moe::MoeOutput;

/// Buffers reused across expert steps (no allocation in the steady state).
#[derive(Debug, Default, Clone)]
pub struct ExpertStepBuffers {
    /// `ε` per sample, row-major `N x d` with `N = B·Z·V`, sample `(b, z, v)` at
    /// `(b·Z + z)·V + v`.
    pub eps: Vec<f32>,
    /// `a = μ + L ε` per sample.
    pub actions: Vec<f32>,
    /// The state of each sample, row-major `N x d_s`.
    pub states: Vec<f32>,
    /// Teacher noise level per sample.
    pub noise_levels: Vec<f32>,
    /// Teacher score per sample.
    pub score: Vec<f32>,
    /// `E_ε[g]` per (state, expert), `B·Z x d`.
    pub mean_g: Vec<f32>,
    /// `E_ε[g εᵀ]` per (state, expert), `B·Z x d·d`.
    pub mean_g_eps: Vec<f32>,
    /// Gradient of the experts' loss w.r.t. raw outputs, `B·Z x raw_dim`.
    pub grad_raw: Vec<f32>,
    log_resp: Vec<f32>,
    grad_k: Vec<f32>,
    g: Vec<f32>,
    /// Per snapshot expert at the current state: `L̃_k⁻¹` (`Z x d·d`) and
    /// `log q̃(k|s) − log det L̃_k − d/2 log 2π` (`Z`).
    snap_linv: Vec<f32>,
    snap_log_norm: Vec<f32>,
    diff: Vec<f32>,
}

/// Summary statistics of one expert step, for monitoring.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ExpertStepStats {
    /// Mean noise level the teacher was queried at.
    pub noise_level: f32,
    /// Mean `log q̃(z|a,s)` over samples (0 when experts do not overlap).
    pub log_responsibility: f32,
    /// Mean expert entropy `H[q(a|s,z)]`.
    pub expert_entropy: f32,
    /// Root-mean-square norm of the corrected score `g`.
    pub corrected_score_rms: f32,
}

/// Draws `V` reparameterised samples per (state, expert) from `current`, queries the teacher
/// once for all of them, and writes `E_ε[g]` and `E_ε[g εᵀ]` into `buf.mean_g` and
/// `buf.mean_g_eps`.
///
/// `states` (`B x d_s`) are the states both `current` (the live student) and `snapshot` (the
/// frozen E-step copy `q̃`) were evaluated on.
#[allow(clippy::too_many_arguments)]
pub fn corrected_score_moments<S: ScoreModel + ?Sized>(
    teacher: &mut S,
    current: &MoeOutput,
    snapshot: &MoeOutput,
    states: MatRef<'_, f32>,
    noise: &NoiseSchedule,
    progress: f32,
    vi_samples: usize,
    rng: &mut dyn RngCore,
    buf: &mut ExpertStepBuffers,
) -> Result<ExpertStepStats, CoreError> {
    let (b_n, z_n, d, v_n) = (current.n, current.num_experts, current.action_dim, vi_samples);
    let ds = states.ncols();
    let n = b_n * z_n * v_n;
    buf.eps.resize(n * d, 0.0);
    buf.actions.resize(n * d, 0.0);
    buf.states.resize(n * ds, 0.0);
    buf.noise_levels.resize(n, 0.0);
    buf.score.resize(n * d, 0.0);
    buf.mean_g.resize(b_n * z_n * d, 0.0);
    buf.mean_g_eps.resize(b_n * z_n * d * d, 0.0);
    buf.log_resp.resize(z_n, 0.0);
    buf.grad_k.resize(z_n * d, 0.0);
    buf.g.resize(d, 0.0);
    buf.snap_linv.resize(z_n * d * d, 0.0);
    buf.snap_log_norm.resize(z_n, 0.0);
    buf.diff.resize(d, 0.0);

    // Reparameterised samples a = μ_z(s) + L_z(s) ε and their states.
    vdd_core::fill_standard_normal(rng, &mut buf.eps);
    for b in 0..b_n {
        for z in 0..z_n {
            let (mu, l) = (current.mean(b, z), current.scale(b, z));
            for v in 0..v_n {
                let i = (b * z_n + z) * v_n + v;
                gaussian::sample_into(
                    mu,
                    l,
                    &buf.eps[i * d..(i + 1) * d],
                    &mut buf.actions[i * d..(i + 1) * d],
                );
                for j in 0..ds {
                    buf.states[i * ds + j] = states[(b, j)];
                }
            }
        }
    }

    // One batched teacher call for every sample.
    teacher.draw_noise_levels(noise, progress, rng, &mut buf.noise_levels);
    teacher.score(
        MatRef::from_row_major_slice(&buf.actions, n, d),
        MatRef::from_row_major_slice(&buf.states, n, ds),
        &buf.noise_levels,
        MatMut::from_row_major_slice_mut(&mut buf.score, n, d),
    )?;
    if buf.score.iter().any(|x| !x.is_finite()) {
        return Err(CoreError::NonFinite { what: "teacher score" });
    }

    // Corrected score g = score + ∇ log q̃(z|a,s) and its moments.
    buf.mean_g.fill(0.0);
    buf.mean_g_eps.fill(0.0);
    let inv_v = 1.0 / v_n as f32;
    let (mut sum_log_resp, mut sum_g2) = (0.0f64, 0.0f64);
    let half_d_ln_2pi = 0.5 * d as f32 * gaussian::LN_2PI;
    for b in 0..b_n {
        // The frozen experts at this state, prepared once for all B·Z·V samples' densities:
        // log N(a; μ̃_k, L̃_k L̃_kᵀ) = c_k − ½|L̃_k⁻¹(a − μ̃_k)|², ∇ = −L̃_k⁻ᵀ L̃_k⁻¹ (a − μ̃_k).
        let snap_lg = snapshot.log_gating_row(b);
        for k in 0..z_n {
            let l = snapshot.scale(b, k);
            gaussian::invert_lower(l, d, &mut buf.snap_linv[k * d * d..(k + 1) * d * d]);
            buf.snap_log_norm[k] = snap_lg[k] - gaussian::half_log_det(l, d) - half_d_ln_2pi;
        }
        for z in 0..z_n {
            let bz = b * z_n + z;
            for v in 0..v_n {
                let i = bz * v_n + v;
                let a = &buf.actions[i * d..(i + 1) * d];
                for k in 0..z_n {
                    let mu = snapshot.mean(b, k);
                    let linv = &buf.snap_linv[k * d * d..(k + 1) * d * d];
                    let grad = &mut buf.grad_k[k * d..(k + 1) * d];
                    let mut maha = 0.0;
                    // y = L⁻¹ (a − μ) into `diff`, then grad = −L⁻ᵀ y.
                    for r in 0..d {
                        let mut y = 0.0;
                        for c in 0..=r {
                            y += linv[r * d + c] * (a[c] - mu[c]);
                        }
                        buf.diff[r] = y;
                        maha += y * y;
                    }
                    for c in 0..d {
                        let mut g = 0.0;
                        for r in c..d {
                            g += linv[r * d + c] * buf.diff[r];
                        }
                        grad[c] = -g;
                    }
                    buf.log_resp[k] = buf.snap_log_norm[k] - 0.5 * maha;
                }
                let joint_z = buf.log_resp[z];
                let lse = gaussian::softmax_in_place(&mut buf.log_resp);
                sum_log_resp += f64::from(joint_z - lse);
                let eps = &buf.eps[i * d..(i + 1) * d];
                for j in 0..d {
                    let mut mix = 0.0;
                    for k in 0..z_n {
                        mix += buf.log_resp[k] * buf.grad_k[k * d + j];
                    }
                    let g = buf.score[i * d + j] + buf.grad_k[z * d + j] - mix;
                    buf.g[j] = g;
                    sum_g2 += f64::from(g * g);
                }
                let mg = &mut buf.mean_g[bz * d..(bz + 1) * d];
                for j in 0..d {
                    mg[j] += buf.g[j] * inv_v;
                }
                let mge = &mut buf.mean_g_eps[bz * d * d..(bz + 1) * d * d];
                for r in 0..d {
                    let gr = buf.g[r] * inv_v;
                    for c in 0..d {
                        mge[r * d + c] += gr * eps[c];
                    }
                }
            }
        }
    }
    let entropy: f32 =
        (0..b_n * z_n).map(|k| gaussian::entropy(current.scale(k / z_n, k % z_n), d)).sum::<f32>()
            / (b_n * z_n) as f32;
    Ok(ExpertStepStats {
        noise_level: buf.noise_levels.iter().sum::<f32>() / n as f32,
        log_responsibility: (sum_log_resp / n as f64) as f32,
        expert_entropy: entropy,
        corrected_score_rms: (sum_g2 / n as f64).sqrt() as f32,
    })
}

/// Gradient of the experts' loss `L = −(1/B) Σ_b Σ_z w_z(s_b) J_z(s_b)` with respect to the
/// raw outputs, from the moments in `buf`; written into `buf.grad_raw`.
///
/// `weights` is `B·Z` (row-major), the detached `w_z(s_b)`.
pub fn raw_gradients<E: Expert>(
    expert: &E,
    current: &MoeOutput,
    weights: &[f32],
    buf: &mut ExpertStepBuffers,
) {
    let (b_n, z_n, d, r) = (current.n, current.num_experts, current.action_dim, expert.raw_dim());
    buf.grad_raw.resize(b_n * z_n * r, 0.0);
    for bz in 0..b_n * z_n {
        let out = &mut buf.grad_raw[bz * r..(bz + 1) * r];
        expert.expert_step_grad(
            &current.raw[bz * r..(bz + 1) * r],
            &current.scales[bz * d * d..(bz + 1) * d * d],
            &buf.mean_g[bz * d..(bz + 1) * d],
            &buf.mean_g_eps[bz * d * d..(bz + 1) * d * d],
            out,
        );
        let scale = -weights[bz] / b_n as f32;
        for x in out.iter_mut() {
            *x *= scale;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_support::IsoGmm;
    use approx::assert_relative_eq;
    use vdd_moe::{DiagonalExpert, FullExpert};

    /// A one-state, two-expert mixture output from raw rows.
    fn output<E: Expert>(expert: &E, raws: &[Vec<f32>], log_gating: [f32; 2]) -> MoeOutput {
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

    /// Monte-Carlo `Ĵ_z` with fixed ε: mean of `log π(a) + log q̃(z|a)` plus the entropy.
    fn objective<E: Expert>(
        expert: &E,
        raw_z: &[f32],
        eps: &[f32],
        teacher: &IsoGmm,
        snapshot: &MoeOutput,
        z: usize,
    ) -> f64 {
        let d = expert.action_dim();
        let (mut mu, mut l) = (vec![0.0; d], vec![0.0; d * d]);
        expert.decode(raw_z, &mut mu, &mut l);
        let v_n = eps.len() / d;
        let (mut a, mut resp, mut work) = (vec![0.0; d], vec![0.0; 2], vec![0.0; d]);
        let mut sum = 0.0f64;
        for v in 0..v_n {
            gaussian::sample_into(&mu, &l, &eps[v * d..(v + 1) * d], &mut a);
            snapshot.log_density_and_responsibilities(0, &a, &mut resp, &mut work);
            sum += f64::from(teacher.log_density(&a, 0.0)) + f64::from(resp[z].ln());
        }
        sum / v_n as f64 + f64::from(gaussian::entropy(&l, d))
    }

    fn check_expert_step_gradient<E: Expert>(expert: E, raws: Vec<Vec<f32>>) {
        let d = expert.action_dim();
        let mut teacher =
            IsoGmm { means: vec![vec![1.0; d], vec![-1.0; d]], std: 0.6, state_dim: 1 };
        let current = output(&expert, &raws, [(0.3f32).ln(), (0.7f32).ln()]);
        // The frozen snapshot q̃ differs from the live student, as after an expert update.
        let snap_raws: Vec<Vec<f32>> =
            raws.iter().map(|r| r.iter().map(|x| x * 0.8 + 0.05).collect()).collect();
        let snapshot = output(&expert, &snap_raws, [(0.4f32).ln(), (0.6f32).ln()]);
        let states = faer::Mat::<f32>::zeros(1, 1);
        let v_n = 16;
        let seeds = vdd_core::Seeds::new(5);
        let mut buf = ExpertStepBuffers::default();
        corrected_score_moments(
            &mut teacher,
            &current,
            &snapshot,
            states.as_ref(),
            &NoiseSchedule::Fixed { level: 0.0 },
            0.0,
            v_n,
            &mut seeds.stream("eps"),
            &mut buf,
        )
        .unwrap();
        for z in 0..2 {
            let r = expert.raw_dim();
            let mut grad = vec![0.0; r];
            expert.expert_step_grad(
                &raws[z],
                current.scale(0, z),
                &buf.mean_g[z * d..(z + 1) * d],
                &buf.mean_g_eps[z * d * d..(z + 1) * d * d],
                &mut grad,
            );
            let eps = &buf.eps[z * v_n * d..(z + 1) * v_n * d];
            for k in 0..r {
                let h = 1e-3f32;
                let mut p = raws[z].clone();
                p[k] += h;
                let mut m = raws[z].clone();
                m[k] -= h;
                let fd = (objective(&expert, &p, eps, &teacher, &snapshot, z)
                    - objective(&expert, &m, eps, &teacher, &snapshot, z))
                    / (2.0 * f64::from(h));
                assert_relative_eq!(f64::from(grad[k]), fd, epsilon = 2e-2, max_relative = 2e-2);
            }
        }
    }

    #[test]
    fn diagonal_expert_step_gradient_matches_finite_differences() {
        let e = DiagonalExpert::new(2, 0.8, 1e-4).unwrap();
        check_expert_step_gradient(e, vec![vec![0.4, 0.9, -0.2, 0.3], vec![-0.7, -0.1, 0.1, -0.4]]);
    }

    #[test]
    fn full_expert_step_gradient_matches_finite_differences() {
        let e = FullExpert::new(2, 0.8, 1e-4).unwrap();
        check_expert_step_gradient(
            e,
            vec![vec![0.4, 0.9, -0.2, 0.35, 0.3], vec![-0.7, -0.1, 0.1, -0.25, -0.4]],
        );
    }
}
