//! The exact Gaussian-mixture teacher: `π(a|s) = Σ_k w_k N(a; μ_k, Σ_k)`, whose noise-smoothed
//! density `π_σ = Σ_k w_k N(μ_k, Σ_k + σ² I)` — and therefore whose score — is known in closed
//! form at every noise level `σ`. Tests and the toy tasks distil it; learned teachers are
//! compared against it.
//!
//! ```
//! use faer::Mat;
//! use vdd_core::ScoreModel;
//! use vdd_core::gmm::GmmTeacher;
//!
//! let mut teacher = GmmTeacher::circle_toy(); // 8 modes on a circle of radius 2, std 0.5
//! let a = Mat::from_fn(1, 2, |_, j| if j == 0 { 2.0 } else { 0.0 }); // on mode 0
//! let s = Mat::<f32>::zeros(1, 1);
//! let mut score = Mat::<f32>::zeros(1, 2);
//! teacher.score(a.as_ref(), s.as_ref(), &[0.1], score.as_mut()).unwrap();
//! assert!(score[(0, 0)].abs() < 0.1); // a mode is (nearly) a stationary point
//! ```

use std::sync::Arc;

use crate::gaussian::{self, LN_2PI};
use crate::lanes;
use crate::{CoreError, Result, ScoreModel, check_finite, check_score_args, check_shape};
use faer::{Mat, MatMut, MatRef};
use rand::{Rng as _, RngCore};

/// A Gaussian mixture in `dim` dimensions at one state.
#[derive(Debug, Clone, PartialEq)]
pub struct Gmm {
    dim: usize,
    log_weights: Vec<f32>,
    means: Vec<f32>,
    /// `K` covariances, row-major `d x d` each.
    covariances: Vec<f32>,
    /// Per-component variance when every covariance is `v_k I` (fast path).
    isotropic: Option<Vec<f32>>,
    /// Cholesky factors of the (unsmoothed) covariances, for sampling.
    chols: Vec<f32>,
    /// The means transposed, `[j][k]` (`d x K`), for the vectorised isotropic path.
    means_t: Vec<f32>,
}

impl Gmm {
    /// A mixture with full covariances (`covariances[k]` row-major `d x d`, symmetric positive
    /// definite). Weights must be positive; they are normalised.
    pub fn new(weights: &[f32], means: &[Vec<f32>], covariances: &[Vec<f32>]) -> Result<Self> {
        let k = weights.len();
        if k == 0 || means.len() != k || covariances.len() != k {
            return Err(CoreError::Config(format!(
                "a GMM needs K >= 1 weights, means and covariances, got {k}, {}, {}",
                means.len(),
                covariances.len()
            )));
        }
        let d = means[0].len();
        if d == 0 {
            return Err(CoreError::Config("a GMM needs dimension >= 1".into()));
        }
        let total: f32 = weights.iter().sum();
        if weights.iter().any(|w| !(w.is_finite() && *w > 0.0)) || !total.is_finite() {
            return Err(CoreError::Config(format!(
                "GMM weights must be positive, got {weights:?}"
            )));
        }
        let mut flat_means = Vec::with_capacity(k * d);
        let mut flat_covs = Vec::with_capacity(k * d * d);
        let mut chols = Vec::with_capacity(k * d * d);
        for (i, (m, c)) in means.iter().zip(covariances).enumerate() {
            if m.len() != d || c.len() != d * d {
                return Err(CoreError::Config(format!(
                    "component {i}: mean has {} entries and covariance {}, expected {d} and {}",
                    m.len(),
                    c.len(),
                    d * d
                )));
            }
            crate::check_finite_slice("GMM mean", m)?;
            let symmetric = (0..d).all(|r| (0..d).all(|s| c[r * d + s] == c[s * d + r]));
            let mut l = c.clone();
            if !symmetric || !gaussian::cholesky_in_place(&mut l, d) {
                return Err(CoreError::Config(format!(
                    "component {i}: covariance is not symmetric positive definite"
                )));
            }
            flat_means.extend_from_slice(m);
            flat_covs.extend_from_slice(c);
            chols.extend_from_slice(&l);
        }
        let iso: Option<Vec<f32>> = (0..k)
            .map(|i| {
                let c = &flat_covs[i * d * d..(i + 1) * d * d];
                let v = c[0];
                let is_iso =
                    (0..d).all(|r| (0..d).all(|s| c[r * d + s] == if r == s { v } else { 0.0 }));
                is_iso.then_some(v)
            })
            .collect();
        Ok(Self {
            dim: d,
            log_weights: weights.iter().map(|w| (w / total).ln()).collect(),
            covariances: flat_covs,
            isotropic: iso,
            chols,
            means_t: (0..d * k).map(|jk| flat_means[(jk % k) * d + jk / k]).collect(),
            means: flat_means,
        })
    }

    /// A mixture whose components all have covariance `std² I`.
    pub fn isotropic(weights: &[f32], means: &[Vec<f32>], std: f32) -> Result<Self> {
        if !(std.is_finite() && std > 0.0) {
            return Err(CoreError::Config(format!("GMM std must be positive, got {std}")));
        }
        let d = means.first().map_or(0, Vec::len);
        let cov: Vec<f32> =
            (0..d * d).map(|i| if i % (d + 1) == 0 { std * std } else { 0.0 }).collect();
        Self::new(weights, means, &vec![cov; means.len()])
    }

    /// `k` equally weighted 2-D modes on a circle of `radius`, mode `i` at angle
    /// `offset + 2πi/k`, each with covariance `std² I`.
    pub fn circle(k: usize, radius: f32, std: f32, offset: f32) -> Result<Self> {
        let means: Vec<Vec<f32>> = (0..k)
            .map(|i| {
                let t = offset + std::f32::consts::TAU * i as f32 / k as f32;
                vec![radius * t.cos(), radius * t.sin()]
            })
            .collect();
        Self::isotropic(&vec![1.0; k], &means, std)
    }

    /// Dimension of the actions.
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// Number of components `K`.
    pub fn num_components(&self) -> usize {
        self.log_weights.len()
    }

    /// Mean of component `k`.
    pub fn mean(&self, k: usize) -> &[f32] {
        &self.means[k * self.dim..(k + 1) * self.dim]
    }

    /// Normalised weight of component `k`.
    pub fn weight(&self, k: usize) -> f32 {
        self.log_weights[k].exp()
    }

    /// Covariance of component `k` (row-major `d x d`).
    pub fn covariance(&self, k: usize) -> &[f32] {
        let dd = self.dim * self.dim;
        &self.covariances[k * dd..(k + 1) * dd]
    }

    /// `log π_σ(a)`, the log-density of the mixture smoothed by `N(0, σ² I)`.
    pub fn log_density(&self, action: &[f32], sigma: f32) -> Result<f32> {
        crate::check_len("action", action.len(), self.dim)?;
        let mut ws = Workspace::default();
        ws.prepare(self, sigma)?;
        Ok(ws.eval(self, action, None))
    }

    /// Draws one sample into `out`.
    pub fn sample_into(&self, rng: &mut dyn RngCore, out: &mut [f32]) {
        let u: f32 = rng.random();
        let mut acc = 0.0;
        let mut k = self.num_components() - 1;
        for (i, lw) in self.log_weights.iter().enumerate() {
            acc += lw.exp();
            if u < acc {
                k = i;
                break;
            }
        }
        let d = self.dim;
        let mut eps = [0.0f32; 16];
        let mut big;
        let eps: &mut [f32] = if d <= 16 {
            &mut eps[..d]
        } else {
            big = vec![0.0; d];
            &mut big
        };
        crate::fill_standard_normal(rng, eps);
        gaussian::sample_into(self.mean(k), &self.chols[k * d * d..(k + 1) * d * d], eps, out);
    }
}

/// Per-noise-level caches: Cholesky factors of `Σ_k + σ² I` (or the smoothed variances on the
/// isotropic fast path) and scratch, reused across rows that share the noise level.
#[derive(Debug, Clone, Default)]
struct Workspace {
    sigma: f32,
    valid: bool,
    /// Inverse smoothed variances `1 / (v_k + σ²)` (isotropic path).
    inv_var: Vec<f32>,
    /// Cholesky factors of `Σ_k + σ² I` (full path).
    chols: Vec<f32>,
    /// `log w_k − ½ log det(Σ_k + σ² I) − d/2 log 2π`.
    log_norm: Vec<f32>,
    log_post: Vec<f32>,
    grads: Vec<f32>,
}

impl Workspace {
    fn prepare(&mut self, gmm: &Gmm, sigma: f32) -> Result<()> {
        if self.valid && self.sigma == sigma {
            return Ok(());
        }
        if !(sigma.is_finite() && sigma >= 0.0) {
            return Err(CoreError::NonFinite { what: "noise level (σ must be finite and >= 0)" });
        }
        let (k, d) = (gmm.num_components(), gmm.dim);
        let s2 = sigma * sigma;
        self.log_norm.resize(k, 0.0);
        self.log_post.resize(k, 0.0);
        self.grads.resize(k * d, 0.0);
        if let Some(iso) = &gmm.isotropic {
            self.inv_var.clear();
            self.inv_var.extend(iso.iter().map(|v| 1.0 / (v + s2)));
            for i in 0..k {
                let v = iso[i] + s2;
                self.log_norm[i] = gmm.log_weights[i] - 0.5 * d as f32 * (v.ln() + LN_2PI);
            }
        } else {
            self.chols.clear();
            self.chols.extend_from_slice(&gmm.covariances);
            for i in 0..k {
                let l = &mut self.chols[i * d * d..(i + 1) * d * d];
                for j in 0..d {
                    l[j * d + j] += s2;
                }
                if !gaussian::cholesky_in_place(l, d) {
                    return Err(CoreError::Config(
                        "smoothed covariance is not positive definite".into(),
                    ));
                }
                self.log_norm[i] =
                    gmm.log_weights[i] - gaussian::half_log_det(l, d) - 0.5 * d as f32 * LN_2PI;
            }
        }
        self.sigma = sigma;
        self.valid = true;
        Ok(())
    }

    /// `log π_σ(a)`, or, with `score`, writes `∇_a log π_σ(a)` there (and returns NaN).
    #[inline(always)]
    fn eval(&mut self, gmm: &Gmm, a: &[f32], score: Option<&mut [f32]>) -> f32 {
        self.eval_sized(gmm.num_components(), gmm.dim, gmm, a, score)
    }

    /// [`Workspace::eval`] with the sizes passed in, so callers can make them constants.
    #[inline(always)]
    fn eval_sized(
        &mut self,
        k: usize,
        d: usize,
        gmm: &Gmm,
        a: &[f32],
        score: Option<&mut [f32]>,
    ) -> f32 {
        debug_assert_eq!((k, d), (gmm.num_components(), gmm.dim));
        let post = &mut self.log_post[..k];
        if gmm.isotropic.is_some() {
            // Fast path, vectorised over components (k innermost):
            // log w_k N = c_k − ½|a − μ_k|² / v_k.
            let inv_var = &self.inv_var[..k];
            let maha = &mut self.grads[..k];
            maha.fill(0.0);
            for j in 0..d {
                let m = &gmm.means_t[j * k..(j + 1) * k];
                let aj = a[j];
                for c in 0..k {
                    let diff = aj - m[c];
                    maha[c] += diff * diff;
                }
            }
            for c in 0..k {
                post[c] = self.log_norm[c] - 0.5 * maha[c] * inv_var[c];
            }
        } else {
            for i in 0..k {
                let l = &self.chols[i * d * d..(i + 1) * d * d];
                let g = &mut self.grads[i * d..(i + 1) * d];
                let lp = gaussian::log_density_and_grad(a, gmm.mean(i), l, g);
                // `log_density_and_grad` includes the normaliser; keep only the weight here.
                post[i] = gmm.log_weights[i] + lp;
            }
        }
        let max = post.iter().copied().fold(f32::NEG_INFINITY, f32::max);
        for p in post.iter_mut() {
            *p = gaussian::exp_fast(*p - max);
        }
        let total: f32 = post.iter().sum();
        let Some(out) = score else {
            return max + total.ln();
        };
        let inv_total = 1.0 / total;
        if gmm.isotropic.is_some() {
            // ∇ = −Σ_k p_k (a − μ_k) / v_k = −(a Σ_k w_k − Σ_k w_k μ_k), w_k = p_k / v_k.
            let w = &mut self.grads[..k];
            let mut sum_w = 0.0;
            for c in 0..k {
                w[c] = post[c] * inv_total * self.inv_var[c];
                sum_w += w[c];
            }
            for j in 0..d {
                let m = &gmm.means_t[j * k..(j + 1) * k];
                let wm: f32 = m.iter().zip(w.iter()).map(|(m, w)| m * w).sum();
                out[j] = wm - a[j] * sum_w;
            }
        } else {
            out.fill(0.0);
            for (p, g) in post.iter().zip(self.grads.chunks_exact(d)) {
                let r = p * inv_total;
                for (o, gj) in out.iter_mut().zip(g) {
                    *o += r * gj;
                }
            }
        }
        // The log-density is not needed alongside the score; skip its `ln`.
        f32::NAN
    }
}

type StateMixture = dyn Fn(&[f32]) -> Result<Gmm> + Send + Sync;

#[derive(Clone)]
enum Source {
    Fixed(Gmm),
    Conditional { state_dim: usize, action_dim: usize, mixture: Arc<StateMixture> },
}

/// A state-conditioned Gaussian-mixture teacher with an exact score at every noise level
/// (a VE teacher: noise levels are `σ`).
///
/// Build it from one fixed [`Gmm`] (the state is ignored), from a closure `s ↦ Gmm`, or as one
/// of the paper's toys ([`GmmTeacher::circle_toy`], [`GmmTeacher::rotating_toy`]).
#[derive(Clone)]
pub struct GmmTeacher {
    source: Source,
    state_dim: usize,
    /// Mixture at `cached_state` (conditional teachers only).
    cached: Option<Gmm>,
    cached_state: Vec<f32>,
    ws: Workspace,
    lanes: IsotropicLanes,
}

impl std::fmt::Debug for GmmTeacher {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GmmTeacher")
            .field("state_dim", &self.state_dim)
            .field("action_dim", &self.action_dim())
            .field("conditional", &matches!(self.source, Source::Conditional { .. }))
            .finish()
    }
}

impl GmmTeacher {
    /// A teacher whose mixture does not depend on the state (`state_dim` columns are ignored).
    pub fn fixed(gmm: Gmm, state_dim: usize) -> Self {
        Self {
            source: Source::Fixed(gmm),
            state_dim,
            cached: None,
            cached_state: Vec::new(),
            ws: Workspace::default(),
            lanes: IsotropicLanes::default(),
        }
    }

    /// A teacher whose mixture at state `s` is `mixture(s)`; the closure must return mixtures of
    /// dimension `action_dim`. Consecutive rows with the same state reuse one evaluation.
    pub fn conditional(
        state_dim: usize,
        action_dim: usize,
        mixture: impl Fn(&[f32]) -> Result<Gmm> + Send + Sync + 'static,
    ) -> Self {
        Self {
            source: Source::Conditional { state_dim, action_dim, mixture: Arc::new(mixture) },
            state_dim,
            cached: None,
            cached_state: Vec::new(),
            ws: Workspace::default(),
            lanes: IsotropicLanes::default(),
        }
    }

    /// Equally weighted isotropic modes (`std` each), state of dimension 1 ignored.
    pub fn isotropic(weights: &[f32], means: &[Vec<f32>], std: f32) -> Result<Self> {
        Ok(Self::fixed(Gmm::isotropic(weights, means, std)?, 1))
    }

    /// The paper's toy: 8 modes on a circle of radius 2, std 0.5, one (ignored) 1-D state.
    pub fn circle_toy() -> Self {
        Self::fixed(Gmm::circle(8, 2.0, 0.5, 0.0).expect("valid constants"), 1)
    }

    /// `n` pairs of [`GmmTeacher::circle_toy`]: states all zero (`n x 1`) and actions drawn
    /// from `rng` (`n x 2`), the data of the recipes' `toy-gmm` and its teachers' benchmark.
    ///
    /// ```
    /// use vdd_core::{Seeds, gmm::GmmTeacher};
    /// let (s, a) = GmmTeacher::circle_toy_data(100, &mut Seeds::new(0).stream("toy-data"))?;
    /// assert_eq!((s.nrows(), s.ncols(), a.ncols()), (100, 1, 2));
    /// # Ok::<(), vdd_core::CoreError>(())
    /// ```
    pub fn circle_toy_data(n: usize, rng: &mut dyn RngCore) -> Result<(Mat<f32>, Mat<f32>)> {
        let states = Mat::<f32>::zeros(n, 1);
        let actions = Self::circle_toy().sample(states.as_ref(), rng)?;
        Ok((states, actions))
    }

    /// The rotating-modes toy: `k` modes on a circle of `radius` with std `std`, mode `i` at
    /// angle `s + 2πi/k` for the scalar state `s`.
    pub fn rotating_toy(k: usize, radius: f32, std: f32) -> Result<Self> {
        Gmm::circle(k, radius, std, 0.0)?;
        Ok(Self::conditional(1, 2, move |s| Gmm::circle(k, radius, std, s[0])))
    }

    /// The mixture at `state`.
    pub fn mixture_at(&self, state: &[f32]) -> Result<Gmm> {
        crate::check_len("state", state.len(), self.state_dim)?;
        match &self.source {
            Source::Fixed(g) => Ok(g.clone()),
            Source::Conditional { mixture, action_dim, .. } => {
                let g = mixture(state)?;
                crate::check_len("mixture dimension", g.dim, *action_dim)?;
                Ok(g)
            }
        }
    }

    /// Makes the mixture for `state` current (cached for conditional teachers); returns whether
    /// it changed.
    fn select(&mut self, state: &[f32]) -> Result<()> {
        if let Source::Conditional { mixture, action_dim, .. } = &self.source {
            if self.cached.is_none() || self.cached_state != state {
                let g = mixture(state)?;
                crate::check_len("mixture dimension", g.dim, *action_dim)?;
                self.cached = Some(g);
                self.cached_state.clear();
                self.cached_state.extend_from_slice(state);
                self.ws.valid = false;
            }
        }
        Ok(())
    }

    fn current(&self) -> &Gmm {
        match &self.source {
            Source::Fixed(g) => g,
            Source::Conditional { .. } => self.cached.as_ref().expect("select() ran first"),
        }
    }

    /// `log π_σ(a|s)` for each row, written into `out` (length `n`).
    pub fn log_density_batch(
        &mut self,
        actions: MatRef<'_, f32>,
        states: MatRef<'_, f32>,
        sigma: f32,
        out: &mut [f32],
    ) -> Result<()> {
        let n = actions.nrows();
        check_shape("actions", actions, n, self.action_dim())?;
        check_shape("states", states, n, self.state_dim)?;
        crate::check_len("log-density output", out.len(), n)?;
        let d = self.action_dim();
        let mut a = vec![0.0f32; d];
        let mut s = vec![0.0f32; self.state_dim];
        for i in 0..n {
            row_into(states, i, &mut s);
            row_into(actions, i, &mut a);
            self.select(&s)?;
            let gmm = match &self.source {
                Source::Fixed(g) => g,
                Source::Conditional { .. } => self.cached.as_ref().expect("selected"),
            };
            self.ws.prepare(gmm, sigma)?;
            out[i] = self.ws.eval(gmm, &a, None);
        }
        Ok(())
    }

    /// `log π_σ(a|s)` for one state-action pair.
    pub fn log_density(&self, state: &[f32], action: &[f32], sigma: f32) -> Result<f32> {
        self.mixture_at(state)?.log_density(action, sigma)
    }

    /// One clean action per state row (`n x action_dim`).
    pub fn sample(&mut self, states: MatRef<'_, f32>, rng: &mut dyn RngCore) -> Result<Mat<f32>> {
        let mut out = Mat::zeros(states.nrows(), self.action_dim());
        self.sample_actions(states, rng, out.as_mut())?;
        Ok(out)
    }
}

fn row_into(m: MatRef<'_, f32>, i: usize, out: &mut [f32]) {
    for (j, o) in out.iter_mut().enumerate() {
        *o = m[(i, j)];
    }
}

impl GmmTeacher {
    #[inline(always)]
    /// The score row by row; `k` is the component count, or 0 to read it from the mixture.
    fn score_rows(
        &mut self,
        d: usize,
        k: usize,
        actions: MatRef<'_, f32>,
        states: MatRef<'_, f32>,
        noise_levels: &[f32],
        mut out: MatMut<'_, f32>,
    ) -> Result<()> {
        let (mut a_small, mut g_small) = ([0.0f32; 16], [0.0f32; 16]);
        let (mut a_big, mut g_big) = (Vec::new(), Vec::new());
        let (a, g): (&mut [f32], &mut [f32]) = if d <= 16 {
            (&mut a_small[..d], &mut g_small[..d])
        } else {
            a_big.resize(d, 0.0);
            g_big.resize(d, 0.0);
            (&mut a_big, &mut g_big)
        };
        let mut s = vec![0.0f32; self.state_dim];
        let conditional = matches!(self.source, Source::Conditional { .. });
        for i in 0..actions.nrows() {
            if conditional {
                row_into(states, i, &mut s);
                self.select(&s)?;
            }
            row_into(actions, i, a);
            let gmm = match &self.source {
                Source::Fixed(g) => g,
                Source::Conditional { .. } => self.cached.as_ref().expect("selected"),
            };
            self.ws.prepare(gmm, noise_levels[i])?;
            let k = if k == 0 { gmm.num_components() } else { k };
            self.ws.eval_sized(k, d, gmm, a, Some(g));
            for j in 0..d {
                out[(i, j)] = g[j];
            }
        }
        Ok(())
    }
}

/// Rows per block of the vectorised isotropic score.
const BLOCK: usize = 64;

/// Lanes (`[component or dimension][row]`) of the blocked isotropic score.
#[derive(Debug, Default, Clone)]
struct IsotropicLanes {
    actions: Vec<f32>,
    diff: Vec<f32>,
    joint: Vec<f32>,
    max: Vec<f32>,
    total: Vec<f32>,
    weight_sum: Vec<f32>,
    weighted_means: Vec<f32>,
}

impl GmmTeacher {
    /// The score of a fixed isotropic mixture, in blocks of up to [`BLOCK`] consecutive rows
    /// sharing a noise level: one lane per component, rows innermost, so every operation is
    /// element-wise over rows and vectorises.
    ///
    /// `∇ log π_σ(a) = Σ_k w_k (μ_k − a) / Σ_k p_k` with `p_k = w_k N(a; μ_k, (v_k + σ²) I)`
    /// unnormalised by the max over k and `w_k = p_k / (v_k + σ²)`.
    fn score_isotropic_blocks(
        &mut self,
        actions: MatRef<'_, f32>,
        noise_levels: &[f32],
        mut out: MatMut<'_, f32>,
    ) -> Result<()> {
        let Source::Fixed(gmm) = &self.source else { unreachable!("fixed mixtures only") };
        let (n, d, k) = (actions.nrows(), gmm.dim, gmm.num_components());
        let b = &mut self.lanes;
        b.actions.resize(d * BLOCK, 0.0);
        b.diff.resize(BLOCK, 0.0);
        b.joint.resize(k * BLOCK, 0.0);
        b.weighted_means.resize(d * BLOCK, 0.0);
        for v in [&mut b.max, &mut b.total, &mut b.weight_sum] {
            v.resize(BLOCK, 0.0);
        }
        let mut i0 = 0;
        while i0 < n {
            let sigma = noise_levels[i0];
            let len = noise_levels[i0..n.min(i0 + BLOCK)]
                .iter()
                .position(|&s| s != sigma)
                .unwrap_or(n.min(i0 + BLOCK) - i0);
            self.ws.prepare(gmm, sigma)?;
            let lane = |i: usize| i * len..(i + 1) * len;
            for j in 0..d {
                let a = &mut b.actions[lane(j)];
                for (t, a) in a.iter_mut().enumerate() {
                    *a = actions[(i0 + t, j)];
                }
            }
            // log w_k N(a; μ_k, (v_k + σ²) I) = c_k − ½ |a − μ_k|² / (v_k + σ²).
            for c in 0..k {
                let joint = &mut b.joint[lane(c)];
                joint.fill(self.ws.log_norm[c]);
                let root_inv_var = self.ws.inv_var[c].sqrt();
                for j in 0..d {
                    let diff = &mut b.diff[..len];
                    diff.fill(0.0);
                    lanes::add_scaled_diff(
                        diff,
                        root_inv_var,
                        &b.actions[lane(j)],
                        gmm.means_t[j * k + c],
                    );
                    lanes::sub_half_square(joint, diff);
                }
            }
            let (max, total) = (&mut b.max[..len], &mut b.total[..len]);
            max.fill(f32::NEG_INFINITY);
            for c in 0..k {
                lanes::max_into(max, &b.joint[lane(c)]);
            }
            total.fill(0.0);
            let weight_sum = &mut b.weight_sum[..len];
            weight_sum.fill(0.0);
            b.weighted_means[..d * len].fill(0.0);
            for c in 0..k {
                let p = &mut b.joint[lane(c)];
                lanes::exp_shifted(p, max, total);
                let iv = self.ws.inv_var[c];
                lanes::add_scaled(weight_sum, iv, p);
                for j in 0..d {
                    let m = gmm.means_t[j * k + c];
                    lanes::add_scaled(&mut b.weighted_means[lane(j)], iv * m, p);
                }
            }
            for j in 0..d {
                let (wm, a) = (&b.weighted_means[lane(j)], &b.actions[lane(j)]);
                for t in 0..len {
                    out[(i0 + t, j)] = (wm[t] - a[t] * weight_sum[t]) / total[t];
                }
            }
            i0 += len;
        }
        Ok(())
    }
}

impl ScoreModel for GmmTeacher {
    fn action_dim(&self) -> usize {
        match &self.source {
            Source::Fixed(g) => g.dim,
            Source::Conditional { action_dim, .. } => *action_dim,
        }
    }

    fn state_dim(&self) -> usize {
        match &self.source {
            Source::Fixed(_) => self.state_dim,
            Source::Conditional { state_dim, .. } => *state_dim,
        }
    }

    fn score(
        &mut self,
        actions: MatRef<'_, f32>,
        states: MatRef<'_, f32>,
        noise_levels: &[f32],
        out: MatMut<'_, f32>,
    ) -> Result<()> {
        check_score_args(self, actions, states, noise_levels, out.as_ref())?;
        check_finite("actions", actions)?;
        // Constant copies of the row loop for small dimensions and component counts (unrolled,
        // no bounds checks); a conditional teacher's count is only known per state.
        let k = match &self.source {
            Source::Fixed(g) if g.isotropic.is_some() => {
                return self.score_isotropic_blocks(actions, noise_levels, out);
            }
            Source::Fixed(g) => g.num_components(),
            Source::Conditional { .. } => 0,
        };
        match (self.action_dim(), k) {
            (2, 4) => self.score_rows(2, 4, actions, states, noise_levels, out),
            (2, 8) => self.score_rows(2, 8, actions, states, noise_levels, out),
            (1, _) => self.score_rows(1, 0, actions, states, noise_levels, out),
            (2, _) => self.score_rows(2, 0, actions, states, noise_levels, out),
            (3, _) => self.score_rows(3, 0, actions, states, noise_levels, out),
            (4, _) => self.score_rows(4, 0, actions, states, noise_levels, out),
            (d, _) => self.score_rows(d, 0, actions, states, noise_levels, out),
        }
    }

    fn sample_actions(
        &mut self,
        states: MatRef<'_, f32>,
        rng: &mut dyn RngCore,
        mut out: MatMut<'_, f32>,
    ) -> Result<()> {
        let n = states.nrows();
        check_shape("states", states, n, self.state_dim())?;
        check_shape("sampled actions", out.as_ref(), n, self.action_dim())?;
        let d = self.action_dim();
        let mut a = vec![0.0f32; d];
        let mut s = vec![0.0f32; self.state_dim];
        for i in 0..n {
            row_into(states, i, &mut s);
            self.select(&s)?;
            self.current().sample_into(rng, &mut a);
            for j in 0..d {
                out[(i, j)] = a[j];
            }
        }
        Ok(())
    }

    /// VE levels on `(0, ∞)`: the mixture smoothed by `N(0, σ² I)` is a VE marginal
    /// (`D = a + σ² s`), and the score is exact at every level.
    fn noise_process(&self) -> Option<&dyn crate::NoiseProcess> {
        static EXACT: crate::VeProcess = crate::VeProcess { min: 0.0, max: f32::INFINITY };
        Some(&EXACT)
    }
    fn fork(&self) -> Option<Box<dyn ScoreModel + Send>> {
        Some(Box::new(self.clone()))
    }
}

pub mod family;
#[cfg(test)]
mod tests;
