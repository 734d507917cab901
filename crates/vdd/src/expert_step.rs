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
use vdd_core::lanes::{
    add_product, add_scaled, add_scaled_diff, dot, exp_shifted, max_into, sub_half_square,
};
use vdd_core::{CoreError, Expert, NoiseSchedule, ScoreModel};
use vdd_moe::MoeOutput;

use crate::both_sides::{BothSidesView, fold_into_moments, noised_cholesky};

/// The experts each state of an expert step trains, when not all of them do
/// ([`crate::VddConfig::experts_per_state`]): state `b`'s `k = per_state` experts are
/// `experts[b·k..(b + 1)·k]`, distinct, each below `Z`. The samples of the step are then
/// `B·k·V`, sample `(b, j, v)` of expert `experts[b·k + j]` at `(b·k + j)·V + v`, and the
/// moments of the other (state, expert) pairs are zero.
#[derive(Debug, Clone, Copy)]
pub struct ExpertSubset<'a> {
    /// The chosen experts, `B·k`.
    pub experts: &'a [u32],
    /// `k`, the experts per state.
    pub per_state: usize,
}

impl<'a> ExpertSubset<'a> {
    /// The part of the subset that belongs to the states `states` of its batch.
    pub fn states(&self, states: std::ops::Range<usize>) -> ExpertSubset<'a> {
        let k = self.per_state;
        ExpertSubset { experts: &self.experts[states.start * k..states.end * k], per_state: k }
    }

    /// Checks the lengths against `b_n` states and the indices against `z_n` experts.
    fn check(&self, b_n: usize, z_n: usize) -> Result<(), CoreError> {
        vdd_core::check_len("expert subset", self.experts.len(), b_n * self.per_state)?;
        match self.experts.iter().find(|&&z| z as usize >= z_n) {
            Some(z) => Err(CoreError::Config(format!("expert subset names expert {z} of {z_n}"))),
            None => Ok(()),
        }
    }
}

/// Buffers reused across expert steps (no allocation in the steady state).
#[derive(Debug, Default, Clone)]
pub struct ExpertStepBuffers {
    /// `ε` per sample, row-major `N x d` with `N = B·Z·V`, sample `(b, z, v)` at
    /// `(b·Z + z)·V + v` (with an [`ExpertSubset`] of `k` experts per state, `N = B·k·V`).
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
    /// Per snapshot expert at the current state: `L̃_k⁻¹` (`Z x d·d`) and
    /// `log q̃(k|s) − log det L̃_k − d/2 log 2π` (`Z`).
    snap_linv: Vec<f32>,
    snap_log_norm: Vec<f32>,
    snap_means: Vec<f32>,
    /// `0..Z`: every expert of a state, when there is no [`ExpertSubset`].
    all_experts: Vec<u32>,
    diff_dd: Vec<f32>,
    /// Scratch of the noised covariances ([`crate::both_sides`]): a Cholesky factor, a column.
    chol_dd: Vec<f32>,
    col_d: Vec<f32>,
    lanes: LaneScratch,
}

/// Scratch of the corrected-score kernel for the samples of one pass (some experts of one
/// state, [`LANES_PER_PASS`]), in structure-of-arrays layout: every per-sample quantity is a
/// lane `[..][t]` with the sample index `t` innermost, so all arithmetic is element-wise over samples and vectorises (no
/// horizontal reductions over experts per sample).
#[derive(Debug, Default, Clone)]
struct LaneScratch {
    /// Actions, `ε` and teacher scores as `[j][t]` (`d x` samples each).
    actions: Vec<f32>,
    eps: Vec<f32>,
    score: Vec<f32>,
    /// `y = L̃_k⁻¹ (a − μ̃_k)` for the current k, `[r][t]`.
    y: Vec<f32>,
    /// `log q̃(k) N(a; μ̃_k, Σ̃_k)`, then the unnormalised responsibilities, `[k][t]`.
    joint: Vec<f32>,
    /// `∇_a log N(a; μ̃_k, Σ̃_k)`, `[k][j][t]`.
    grad: Vec<f32>,
    /// The corrected score `g`, `[j][t]`.
    g: Vec<f32>,
    /// Per sample: max over k of the joints, sum of the unnormalised responsibilities, and
    /// `log q̃(z|a) + ln(total)`.
    max: Vec<f32>,
    total: Vec<f32>,
    log_resp: Vec<f32>,
}

impl LaneScratch {
    fn resize(&mut self, d: usize, z_n: usize, v_n: usize) {
        for v in [&mut self.actions, &mut self.eps, &mut self.score, &mut self.y, &mut self.g] {
            v.resize(d * v_n, 0.0);
        }
        for v in [&mut self.max, &mut self.total, &mut self.log_resp] {
            v.resize(v_n, 0.0);
        }
        self.joint.resize(z_n * v_n, 0.0);
        self.grad.resize(z_n * d * v_n, 0.0);
    }
}

/// Inputs of the corrected-score kernel for one state: its `K·V` samples (row-major, sample
/// `(j, v)` of slot `j`'s expert at `j·V + v`; `K = Z` without an [`ExpertSubset`]) and the
/// frozen experts prepared for that state.
struct StateBlock<'a> {
    z_n: usize,
    v_n: usize,
    /// The experts this state's samples belong to, slot by slot (`0..Z` without a subset): the
    /// samples of slot `j` are `j·V..(j + 1)·V`.
    experts: &'a [u32],
    actions: &'a [f32],
    eps: &'a [f32],
    score: &'a [f32],
    /// `μ̃` as `[j][k]` (`d x Z`).
    snap_means: &'a [f32],
    /// `L̃⁻¹` as `[r·d + c][k]` (`d·d x Z`).
    snap_linv: &'a [f32],
    /// `log q̃(k|s) − log det L̃_k − d/2 log 2π`.
    snap_log_norm: &'a [f32],
}

/// Outputs (the state's `E[g]`, `E[g εᵀ]`) and scratch of the kernel.
struct StateBlockOut<'a> {
    mean_g: &'a mut [f32],
    mean_g_eps: &'a mut [f32],
    lanes: &'a mut LaneScratch,
}

/// Most samples the corrected-score kernel treats in one pass: the samples of
/// `max(1, LANES_PER_PASS / V)` experts of a state, so that the lanes are long even with few
/// samples per expert (`V = 1`: all `Z` experts of the state at once) while the scratch stays
/// small with many.
const LANES_PER_PASS: usize = 256;

/// Experts per pass of the kernel with `v_n` samples per expert and `z_n` experts (see
/// [`LANES_PER_PASS`]).
fn experts_per_pass(v_n: usize, z_n: usize) -> usize {
    (LANES_PER_PASS / v_n).clamp(1, z_n)
}

impl StateBlock<'_> {
    /// Slots per pass of the kernel ([`experts_per_pass`]).
    fn group(&self) -> usize {
        experts_per_pass(self.v_n, self.experts.len())
    }

    /// Accumulates `E_ε[g]` and `E_ε[g εᵀ]` for every expert at this state; returns the sums
    /// of `log q̃(z|a)` and of `|g|²` over the samples (monitoring).
    #[inline(always)]
    fn run(&self, d: usize, z_n: usize, out: StateBlockOut<'_>) -> (f64, f64) {
        debug_assert_eq!(z_n, self.z_n);
        let (v_n, inv_v) = (self.v_n, 1.0 / self.v_n as f32);
        let (mut sum_log_resp, mut sum_g2) = (0.0f64, 0.0f64);
        let c = out.lanes;
        let (group, slots) = (self.group(), self.experts.len());
        let mut s0 = 0;
        while s0 < slots {
            let s1 = (s0 + group).min(slots);
            let n = (s1 - s0) * v_n;
            // Gather the samples of slots s0..s1 into `[j][t]`, `t = (slot − s0)·V + v`.
            for t in 0..n {
                let i = s0 * v_n + t;
                for j in 0..d {
                    c.actions[j * n + t] = self.actions[i * d + j];
                    c.eps[j * n + t] = self.eps[i * d + j];
                    c.score[j * n + t] = self.score[i * d + j];
                }
            }
            self.corrected_scores(d, z_n, s0, s1, c);
            for slot in s0..s1 {
                let (z, r) =
                    (self.experts[slot] as usize, (slot - s0) * v_n..(slot - s0 + 1) * v_n);
                // Σ log q̃(z|a) = Σ (joint_z − max) − ln Π total: the logs of the totals are
                // taken once per many samples (each total is in [1, Z], so the f64 product
                // stays finite).
                sum_log_resp += f64::from(c.log_resp[r.clone()].iter().sum::<f32>());
                let mut product = 1.0f64;
                for &t in &c.total[r.clone()] {
                    product *= f64::from(t);
                    if product > 1e200 {
                        sum_log_resp -= product.ln();
                        product = 1.0;
                    }
                }
                sum_log_resp -= product.ln();
                // |g|², E[g] and E[g εᵀ].
                let mut g2 = 0.0f32;
                let mg = &mut out.mean_g[z * d..(z + 1) * d];
                let mge = &mut out.mean_g_eps[z * d * d..(z + 1) * d * d];
                for row in 0..d {
                    let gr = &c.g[row * n..(row + 1) * n][r.clone()];
                    g2 += dot(gr, gr);
                    mg[row] = gr.iter().sum::<f32>() * inv_v;
                    for col in 0..d {
                        let e = &c.eps[col * n..(col + 1) * n][r.clone()];
                        mge[row * d + col] = dot(gr, e) * inv_v;
                    }
                }
                sum_g2 += f64::from(g2);
            }
            s0 = s1;
        }
        (sum_log_resp, sum_g2)
    }

    /// The corrected scores `g` of the samples of slots `s0..s1` (gathered in `c`, `n` of
    /// them) into `c.g`, with `log q̃(z|a) + ln(total)` in `c.log_resp` and the totals of the
    /// unnormalised responsibilities in `c.total`.
    #[inline(always)]
    fn corrected_scores(&self, d: usize, z_n: usize, s0: usize, s1: usize, c: &mut LaneScratch) {
        let (v_n, n) = (self.v_n, (s1 - s0) * self.v_n);
        let lane = |i: usize| i * n..(i + 1) * n;
        // Per frozen expert k: y = L̃_k⁻¹ (a − μ̃_k), log q̃(k) N(a; μ̃_k, Σ̃_k) = c_k − ½|y|²,
        // ∇_a log N = −L̃_k⁻ᵀ y.
        for k in 0..z_n {
            let joint = &mut c.joint[lane(k)];
            joint.fill(self.snap_log_norm[k]);
            for r in 0..d {
                let yr = &mut c.y[lane(r)];
                yr.fill(0.0);
                for col in 0..=r {
                    let l = self.snap_linv[(r * d + col) * z_n + k];
                    let m = self.snap_means[col * z_n + k];
                    add_scaled_diff(yr, l, &c.actions[lane(col)], m);
                }
                sub_half_square(joint, yr);
            }
            for col in 0..d {
                let gk = &mut c.grad[lane(k * d + col)];
                gk.fill(0.0);
                for r in col..d {
                    let l = self.snap_linv[(r * d + col) * z_n + k];
                    add_scaled(gk, -l, &c.y[lane(r)]);
                }
            }
        }
        // Responsibilities q̃(k|a) = joint_k / Σ_k joint_k, stabilised by the max over k.
        c.max[..n].fill(f32::NEG_INFINITY);
        for k in 0..z_n {
            max_into(&mut c.max[..n], &c.joint[lane(k)]);
        }
        for slot in s0..s1 {
            let (z, r) = (self.experts[slot] as usize, (slot - s0) * v_n..(slot - s0 + 1) * v_n);
            let own = &c.joint[lane(z)][r.clone()];
            c.log_resp[r.clone()].copy_from_slice(own);
            add_scaled(&mut c.log_resp[r.clone()], -1.0, &c.max[r]);
        }
        c.total[..n].fill(0.0);
        for k in 0..z_n {
            exp_shifted(&mut c.joint[lane(k)], &c.max[..n], &mut c.total[..n]);
        }
        // g = score + ∇ log N(a; μ̃_z, Σ̃_z) − Σ_k q̃(k|a) ∇ log N(a; μ̃_k, Σ̃_k).
        for j in 0..d {
            let g = &mut c.g[lane(j)];
            g.fill(0.0);
            for k in 0..z_n {
                add_product(g, &c.joint[lane(k)], &c.grad[lane(k * d + j)]);
            }
            for slot in s0..s1 {
                let (z, r) =
                    (self.experts[slot] as usize, (slot - s0) * v_n..(slot - s0 + 1) * v_n);
                let gz = &c.grad[lane(z * d + j)][r.clone()];
                let (score, total) = (&c.score[lane(j)][r.clone()], &c.total[r.clone()]);
                let g = &mut g[r];
                for t in 0..v_n {
                    g[t] = score[t] + gz[t] - g[t] / total[t];
                }
            }
        }
    }
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
/// frozen E-step copy `q̃`) were evaluated on. This is [`draw_sample_noise`] (the `ε` and the
/// noise levels, in this order from `rng`), [`moments_from_noise`] and
/// [`MomentSums::stats`].
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
    let n = current.n * current.num_experts * vi_samples;
    let (eps, levels) = (&mut buf.eps, &mut buf.noise_levels);
    draw_sample_noise(&*teacher, noise, progress, rng, n, current.action_dim, eps, levels);
    let sums = moments_from_noise(teacher, current, snapshot, states, vi_samples, None, None, buf)?;
    Ok(sums.stats(&buf.noise_levels, current.n * current.num_experts))
}

/// Draws the randomness of an expert step with `samples` samples of `d` dimensions: first
/// `ε ~ N(0, I)` into `eps` (`samples · d`), then the teacher's noise levels from `noise` at
/// `progress` into `levels` (`samples`); both are resized.
#[allow(clippy::too_many_arguments)]
pub fn draw_sample_noise<S: ScoreModel + ?Sized>(
    teacher: &S,
    noise: &NoiseSchedule,
    progress: f32,
    rng: &mut dyn RngCore,
    samples: usize,
    d: usize,
    eps: &mut Vec<f32>,
    levels: &mut Vec<f32>,
) {
    eps.resize(samples * d, 0.0);
    levels.resize(samples, 0.0);
    vdd_core::fill_standard_normal(rng, eps);
    teacher.draw_noise_levels(noise, progress, rng, levels);
}

/// Sums over the samples and (state, expert) pairs of one [`moments_from_noise`], from which
/// [`MomentSums::stats`] makes the step's statistics; the sums of several chunks of a batch
/// add up ([`MomentSums::add`]).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct MomentSums {
    /// `Σ log q̃(z|a,s)` over the samples.
    pub log_responsibility: f64,
    /// `Σ |g|²` over the samples.
    pub g2: f64,
    /// `Σ H[q(a|s,z)]` over the (state, expert) pairs.
    pub entropy: f32,
}

impl MomentSums {
    /// Adds the sums of another chunk.
    pub fn add(&mut self, other: &MomentSums) {
        self.log_responsibility += other.log_responsibility;
        self.g2 += other.g2;
        self.entropy += other.entropy;
    }

    /// The statistics of a step whose samples were drawn at the noise levels `levels` (one per
    /// sample) from `pairs` (state, expert) pairs.
    pub fn stats(&self, levels: &[f32], pairs: usize) -> ExpertStepStats {
        let n = levels.len();
        ExpertStepStats {
            noise_level: (levels.iter().map(|&l| f64::from(l)).sum::<f64>() / n as f64) as f32,
            log_responsibility: (self.log_responsibility / n as f64) as f32,
            expert_entropy: self.entropy / pairs as f32,
            corrected_score_rms: (self.g2 / n as f64).sqrt() as f32,
        }
    }
}

/// [`corrected_score_moments`] with the `ε` and noise levels already in `buf.eps` and
/// `buf.noise_levels` (`B·Z·V · d` and `B·Z·V`, as [`draw_sample_noise`] writes them): the
/// samples, one batched teacher call, and the moments into `buf.mean_g` and
/// `buf.mean_g_eps`. Returns the sums of the step's statistics.
///
/// With `subset`, only the chosen (state, expert) pairs are sampled and scored (`B·k·V`
/// samples); the other pairs' moments are zero.
///
/// With `both` (noise on both sides, [`crate::both_sides`]), the samples are noised, the
/// snapshot's responsibilities are those of the noised snapshot, and the moments are folded
/// so that [`Expert::expert_step_grad`] gives the gradient of the noised objective.
#[allow(clippy::too_many_arguments)]
pub fn moments_from_noise<S: ScoreModel + ?Sized>(
    teacher: &mut S,
    current: &MoeOutput,
    snapshot: &MoeOutput,
    states: MatRef<'_, f32>,
    vi_samples: usize,
    both: Option<BothSidesView<'_>>,
    subset: Option<ExpertSubset<'_>>,
    buf: &mut ExpertStepBuffers,
) -> Result<MomentSums, CoreError> {
    let z_n = current.num_experts;
    if let Some(subset) = &subset {
        subset.check(current.n, z_n)?;
    }
    let mut all = std::mem::take(&mut buf.all_experts);
    all.clear();
    all.extend(0..z_n as u32);
    let slots = match subset {
        Some(s) => Slots::Subset(s),
        None => Slots::All(&all),
    };
    let sums = moments_of_slots(teacher, current, snapshot, states, vi_samples, both, slots, buf);
    buf.all_experts = all;
    sums
}

/// The experts whose moments an expert step computes: all of them at every state, or an
/// [`ExpertSubset`].
#[derive(Clone, Copy)]
enum Slots<'a> {
    All(&'a [u32]),
    Subset(ExpertSubset<'a>),
}

impl Slots<'_> {
    /// Experts per state.
    fn per_state(&self) -> usize {
        match self {
            Slots::All(all) => all.len(),
            Slots::Subset(s) => s.per_state,
        }
    }

    /// The experts of state `b`, slot by slot.
    fn of(&self, b: usize) -> &[u32] {
        match self {
            Slots::All(all) => all,
            Slots::Subset(s) => s.states(b..b + 1).experts,
        }
    }
}

/// [`moments_from_noise`] for the experts of `slots`.
#[allow(clippy::too_many_arguments)]
fn moments_of_slots<S: ScoreModel + ?Sized>(
    teacher: &mut S,
    current: &MoeOutput,
    snapshot: &MoeOutput,
    states: MatRef<'_, f32>,
    vi_samples: usize,
    both: Option<BothSidesView<'_>>,
    slots: Slots<'_>,
    buf: &mut ExpertStepBuffers,
) -> Result<MomentSums, CoreError> {
    let (b_n, z_n, d, v_n) = (current.n, current.num_experts, current.action_dim, vi_samples);
    let ds = states.ncols();
    let k_n = slots.per_state();
    let n = b_n * k_n * v_n;
    vdd_core::check_len("expert step noise", buf.eps.len(), n * d)?;
    vdd_core::check_len("expert step noise levels", buf.noise_levels.len(), n)?;
    buf.actions.resize(n * d, 0.0);
    buf.states.resize(n * ds, 0.0);
    buf.score.resize(n * d, 0.0);
    buf.mean_g.resize(b_n * z_n * d, 0.0);
    buf.mean_g_eps.resize(b_n * z_n * d * d, 0.0);
    buf.snap_linv.resize(z_n * d * d, 0.0);
    buf.snap_log_norm.resize(z_n, 0.0);
    buf.lanes.resize(d, z_n, experts_per_pass(v_n, k_n) * v_n);
    buf.diff_dd.resize(d * d, 0.0);
    buf.chol_dd.resize(d * d, 0.0);
    buf.col_d.resize(d, 0.0);
    if let Some(both) = &both {
        vdd_core::check_len("noised states", both.scale.len(), b_n)?;
        vdd_core::check_len("noise on both sides", both.eta.len(), n * d)?;
    }

    // Reparameterised samples a = μ_z(s) + L_z(s) ε (noised: k a + β + γ ⊙ η) and their states.
    for b in 0..b_n {
        for (j, &z) in slots.of(b).iter().enumerate() {
            let (mu, l) = (current.mean(b, z as usize), current.scale(b, z as usize));
            for v in 0..v_n {
                let i = (b * k_n + j) * v_n + v;
                gaussian::sample_into(
                    mu,
                    l,
                    &buf.eps[i * d..(i + 1) * d],
                    &mut buf.actions[i * d..(i + 1) * d],
                );
                if let Some(both) = &both {
                    let (k, row) = (both.scale[b], b * d..(b + 1) * d);
                    let (shift, std) = (&both.shift[row.clone()], &both.std[row]);
                    let eta = &both.eta[i * d..(i + 1) * d];
                    for (j, x) in buf.actions[i * d..(i + 1) * d].iter_mut().enumerate() {
                        *x = k * *x + shift[j] + std[j] * eta[j];
                    }
                }
                for j in 0..ds {
                    buf.states[i * ds + j] = states[(b, j)];
                }
            }
        }
    }

    // One batched teacher call for every sample.
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
    let (mut sum_log_resp, mut sum_g2) = (0.0f64, 0.0f64);
    let half_d_ln_2pi = 0.5 * d as f32 * gaussian::LN_2PI;
    buf.snap_means.resize(z_n * d, 0.0);
    for b in 0..b_n {
        // The frozen experts at this state, prepared once for all Z·V samples' densities:
        // log N(a; μ̃_k, L̃_k L̃_kᵀ) = c_k − ½|L̃_k⁻¹(a − μ̃_k)|², ∇ = −L̃_k⁻ᵀ L̃_k⁻¹ (a − μ̃_k).
        let snap_lg = snapshot.log_gating_row(b);
        // Structure-of-arrays layout (expert index innermost) so the per-sample loops over the
        // Z frozen experts vectorise.
        // Noised: N(k μ̃_k + β, k² Σ̃_k + diag(γ²)).
        let noised = both.as_ref().map(|s| {
            let row = b * d..(b + 1) * d;
            (s.scale[b], &s.shift[row.clone()], &s.std[row])
        });
        for k in 0..z_n {
            let l = match noised {
                None => snapshot.scale(b, k),
                Some((scale, _, std)) => {
                    if !noised_cholesky(snapshot.scale(b, k), scale, std, d, &mut buf.chol_dd) {
                        return Err(CoreError::NonFinite { what: "noised snapshot covariance" });
                    }
                    &buf.chol_dd
                }
            };
            gaussian::invert_lower(l, d, &mut buf.diff_dd);
            for rc in 0..d * d {
                buf.snap_linv[rc * z_n + k] = buf.diff_dd[rc];
            }
            buf.snap_log_norm[k] = snap_lg[k] - gaussian::half_log_det(l, d) - half_d_ln_2pi;
            for (j, m) in snapshot.mean(b, k).iter().enumerate() {
                buf.snap_means[j * z_n + k] = match noised {
                    None => *m,
                    Some((scale, shift, _)) => scale * *m + shift[j],
                };
            }
        }
        let rows = b * k_n * v_n..(b + 1) * k_n * v_n;
        let block = StateBlock {
            z_n,
            v_n,
            experts: slots.of(b),
            actions: &buf.actions[rows.start * d..rows.end * d],
            eps: &buf.eps[rows.start * d..rows.end * d],
            score: &buf.score[rows.start * d..rows.end * d],
            snap_means: &buf.snap_means,
            snap_linv: &buf.snap_linv,
            snap_log_norm: &buf.snap_log_norm,
        };
        let out = StateBlockOut {
            mean_g: &mut buf.mean_g[b * z_n * d..(b + 1) * z_n * d],
            mean_g_eps: &mut buf.mean_g_eps[b * z_n * d * d..(b + 1) * z_n * d * d],
            lanes: &mut buf.lanes,
        };
        // Dispatch small dimensions and expert counts to constant copies of the kernel
        // (unrolled loops, no bounds checks); others run the same code with run-time sizes.
        let (lr, g2) = match (d, z_n) {
            (1, 4) => block.run(1, 4, out),
            (1, 8) => block.run(1, 8, out),
            (2, 4) => block.run(2, 4, out),
            (2, 8) => block.run(2, 8, out),
            (2, 16) => block.run(2, 16, out),
            (1, _) => block.run(1, z_n, out),
            (2, _) => block.run(2, z_n, out),
            (3, _) => block.run(3, z_n, out),
            (4, _) => block.run(4, z_n, out),
            (6, _) => block.run(6, z_n, out),
            (8, _) => block.run(8, z_n, out),
            _ => block.run(d, z_n, out),
        };
        sum_log_resp += lr;
        sum_g2 += g2;
        if let Some((scale, _, std)) = noised {
            for &z in slots.of(b) {
                let (z, bz) = (z as usize, b * z_n + z as usize);
                fold_into_moments(
                    current.scale(b, z),
                    scale,
                    std,
                    d,
                    &mut buf.mean_g[bz * d..(bz + 1) * d],
                    &mut buf.mean_g_eps[bz * d * d..(bz + 1) * d * d],
                    &mut buf.chol_dd,
                    &mut buf.col_d,
                )?;
            }
        }
    }
    let entropy: f32 =
        (0..b_n * z_n).map(|k| gaussian::entropy(current.scale(k / z_n, k % z_n), d)).sum::<f32>();
    Ok(MomentSums { log_responsibility: sum_log_resp, g2: sum_g2, entropy })
}

/// Gradient of the experts' loss `L = −(1/B) Σ_b Σ_z w_z(s_b) J_z(s_b)` with respect to the
/// raw outputs, from the moments in `buf`; written into `buf.grad_raw`.
///
/// `weights` is `B·Z` (row-major), the detached `w_z(s_b)`.
///
/// With `subset` (the one the moments were computed for), only the chosen pairs contribute,
/// each weighted by `Z/k`: every pair is chosen with probability `k/Z`
/// ([`crate::VddConfig::experts_per_state`]), so the gradient is an unbiased estimate of the
/// full step's.
pub fn raw_gradients<E: Expert>(
    expert: &E,
    current: &MoeOutput,
    weights: &[f32],
    subset: Option<ExpertSubset<'_>>,
    buf: &mut ExpertStepBuffers,
) {
    raw_gradients_of_chunk(expert, current, weights, current.n, subset, buf)
}

/// [`raw_gradients`] for a chunk of the states of a batch of `batch_size` states: `current`,
/// `weights` and `subset` hold the chunk's states only, and the loss is still the batch's mean.
pub fn raw_gradients_of_chunk<E: Expert>(
    expert: &E,
    current: &MoeOutput,
    weights: &[f32],
    batch_size: usize,
    subset: Option<ExpertSubset<'_>>,
    buf: &mut ExpertStepBuffers,
) {
    let (z_n, d, r) = (current.num_experts, current.action_dim, expert.raw_dim());
    let b_n = batch_size;
    let rows = current.n;
    buf.grad_raw.resize(rows * z_n * r, 0.0);
    if subset.is_some() {
        // The pairs not chosen contribute nothing.
        buf.grad_raw.fill(0.0);
    }
    let mut pair = |bz: usize, factor: f32| {
        let out = &mut buf.grad_raw[bz * r..(bz + 1) * r];
        expert.expert_step_grad(
            &current.raw[bz * r..(bz + 1) * r],
            &current.scales[bz * d * d..(bz + 1) * d * d],
            &buf.mean_g[bz * d..(bz + 1) * d],
            &buf.mean_g_eps[bz * d * d..(bz + 1) * d * d],
            out,
        );
        let scale = -weights[bz] * factor / b_n as f32;
        for x in out.iter_mut() {
            *x *= scale;
        }
    };
    match subset {
        None => (0..rows * z_n).for_each(|bz| pair(bz, 1.0)),
        Some(s) => {
            let factor = z_n as f32 / s.per_state as f32;
            for (i, &z) in s.experts.iter().enumerate() {
                pair((i / s.per_state) * z_n + z as usize, factor);
            }
        }
    }
}

#[cfg(test)]
mod tests_both_sides;

#[cfg(test)]
mod tests;
