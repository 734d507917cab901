//! [`MoeOutput`]: the per-state means, scales and gating of the last forward pass.

use vdd_core::gaussian;

/// The per-state outputs of the last forward pass: for `n` states and `Z` experts, row-major
/// `raw` (`n·Z·raw_dim`), `means` (`n·Z·d`), `scales` (`n·Z·d·d`, lower-triangular `L`) and
/// `log_gating` (`n·Z`, `log q(z|s)`).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct MoeOutput {
    /// Number of states.
    pub n: usize,
    /// Number of experts.
    pub num_experts: usize,
    /// Action dimension.
    pub action_dim: usize,
    /// Raw network outputs per (state, expert).
    pub raw: Vec<f32>,
    /// Means per (state, expert).
    pub means: Vec<f32>,
    /// Scale factors `L` per (state, expert).
    pub scales: Vec<f32>,
    /// `log q(z|s)` per (state, expert).
    pub log_gating: Vec<f32>,
}

impl MoeOutput {
    /// `μ_z(s_b)`.
    ///
    /// # Panics
    /// If `(b, z)` is out of range for the last forward pass (likewise for the other accessors).
    pub fn mean(&self, b: usize, z: usize) -> &[f32] {
        let d = self.action_dim;
        let k = b * self.num_experts + z;
        &self.means[k * d..(k + 1) * d]
    }

    /// `L_z(s_b)` (`d·d`, row-major).
    pub fn scale(&self, b: usize, z: usize) -> &[f32] {
        let dd = self.action_dim * self.action_dim;
        let k = b * self.num_experts + z;
        &self.scales[k * dd..(k + 1) * dd]
    }

    /// `log q(·|s_b)` over the experts.
    pub fn log_gating_row(&self, b: usize) -> &[f32] {
        &self.log_gating[b * self.num_experts..(b + 1) * self.num_experts]
    }

    /// `log q(a|s_b) = logsumexp_z [log q(z|s_b) + log N(a; μ_z, Σ_z)]`; also writes the
    /// responsibilities `q(z|a, s_b)` into `resp` (length `Z`). `work` is scratch of length `d`.
    ///
    /// An action so far from every expert that all densities underflow gets `−∞` and the
    /// gating `q(z|s_b)` as responsibilities (the limit of Bayes' rule for equal likelihoods).
    ///
    /// # Panics
    /// If `b` is not a state of the last forward pass or the slices have the wrong lengths.
    pub fn log_density_and_responsibilities(
        &self,
        b: usize,
        a: &[f32],
        resp: &mut [f32],
        work: &mut [f32],
    ) -> f32 {
        let z_count = self.num_experts;
        let resp = &mut resp[..z_count];
        for (z, r) in resp.iter_mut().enumerate() {
            *r = self.log_gating[b * z_count + z]
                + gaussian::log_density(a, self.mean(b, z), self.scale(b, z), work);
        }
        let lse = gaussian::softmax_in_place(resp);
        if lse.is_finite() {
            return lse;
        }
        for (r, lg) in resp.iter_mut().zip(self.log_gating_row(b)) {
            *r = lg.exp();
        }
        f32::NEG_INFINITY
    }
}
