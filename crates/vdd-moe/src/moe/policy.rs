//! [`Moe`] as a [`Policy`]: acting (gating, then only the chosen expert) and the exact
//! likelihood, on observations normalised here.

use faer::{Mat, MatRef};
use rand::Rng as _;
use vdd_core::gaussian;
use vdd_core::{
    CoreError, Expert, Policy, Seeds, check_act_args, check_finite, check_len, check_shape,
};
use vdd_nn::{Module, ResidualMlp};

use super::{ExpertNets, Hold, Moe};
use crate::error::MoeError;

impl<E: Expert> Policy for Moe<E> {
    fn obs_dim(&self) -> usize {
        self.config.state_dim
    }
    fn action_dim(&self) -> usize {
        self.config.action_dim
    }
    fn seed(&mut self, seed: u64) {
        self.rng = Seeds::new(seed).stream("moe-act");
    }
    /// Ends every row's held expert ([`ActMode::hold_steps`](crate::ActMode::hold_steps)).
    fn reset(&mut self) {
        self.held.clear();
    }
    fn last_experts(&self) -> &[usize] {
        Moe::last_experts(self)
    }

    fn act_into(&mut self, obs: &[f32], action: &mut [f32]) -> vdd_core::Result<()> {
        check_act_args(self, obs, action)?;
        let o = MatRef::from_row_major_slice(obs, 1, obs.len());
        let d = action.len();
        self.act_rows(o, faer::MatMut::from_row_major_slice_mut(action, 1, d))
    }

    fn act_batch(
        &mut self,
        obs: MatRef<'_, f32>,
        actions: faer::MatMut<'_, f32>,
    ) -> vdd_core::Result<()> {
        check_shape("actions", actions.as_ref(), obs.nrows(), self.config.action_dim)?;
        self.act_rows(obs, actions)
    }

    fn has_likelihood(&self) -> bool {
        true
    }

    fn log_likelihood(
        &mut self,
        obs: MatRef<'_, f32>,
        actions: MatRef<'_, f32>,
        out: &mut [f32],
    ) -> vdd_core::Result<()> {
        let n = obs.nrows();
        check_shape("observations", obs, n, self.config.state_dim)?;
        check_shape("actions", actions, n, self.config.action_dim)?;
        check_len("log-likelihood output", out.len(), n)?;
        check_finite("actions", actions)?;
        self.forward_observations(obs)?;
        let log_det = self.log_det_action_scale();
        let mut a = vec![0.0; self.config.action_dim];
        for (b, o) in out.iter_mut().enumerate() {
            for (j, v) in a.iter_mut().enumerate() {
                *v = actions[(b, j)];
            }
            if let Some(norm) = &self.action_normalizer {
                norm.normalize(&mut a);
            }
            *o = self.out.log_density_and_responsibilities(b, &a, &mut self.resp, &mut self.work)
                - log_det;
        }
        Ok(())
    }
}

impl<E: Expert> Moe<E> {
    /// Acting (`Policy::act_into` and `act_batch`): the gating for every state, then for each
    /// state in turn an expert `z ~ q(z|s)` (or the most likely one; or the row's held one,
    /// [`ActMode::hold_steps`](crate::ActMode::hold_steps)) and only that expert's
    /// outputs: its columns of the shared trunk's output layer (or its own network), decoded
    /// into `(μ_z, L_z)`. The action is `μ_z`, or a sample of `N(μ_z, L_z L_zᵀ)`.
    fn act_rows(
        &mut self,
        obs: MatRef<'_, f32>,
        actions: faer::MatMut<'_, f32>,
    ) -> vdd_core::Result<()> {
        self.on_observations(obs, |moe, states| moe.act_on_states(states, actions))
    }

    /// Checks and normalises observations, then runs `f` on the normalised states.
    fn on_observations<T>(
        &mut self,
        obs: MatRef<'_, f32>,
        f: impl FnOnce(&mut Self, MatRef<'_, f32>) -> vdd_core::Result<T>,
    ) -> vdd_core::Result<T> {
        check_shape("observations", obs, obs.nrows(), self.config.state_dim)?;
        check_finite("observations", obs)?;
        self.load_normalized_states(obs);
        // Finite observations can still overflow when normalised (3e38 / a scale below 1).
        check_finite("normalised observations", self.states.as_ref())?;
        let states = std::mem::replace(&mut self.states, Mat::zeros(0, 0));
        let r = f(self, states.as_ref());
        self.states = states;
        r
    }

    fn act_on_states(
        &mut self,
        states: MatRef<'_, f32>,
        mut actions: faer::MatMut<'_, f32>,
    ) -> vdd_core::Result<()> {
        // Inference passes: a backward pass needs a forward first.
        self.gating_pass(states, true).map_err(to_core)?;
        self.experts_forwarded = false;
        let (z, r, d) = (self.config.num_experts, self.expert.raw_dim(), self.config.action_dim);
        let h = self.config.experts_network.hidden_dim;
        let Self {
            experts,
            expert,
            rng,
            out,
            act_work,
            act_mode,
            action_normalizer,
            last_experts,
            held,
            ..
        } = self;
        last_experts.clear();
        if held.len() < states.nrows() {
            held.resize(states.nrows(), Hold::default());
        }
        act_work.resize(r + 3 * d + d * d + h, 0.0);
        let (raw, rest) = act_work.split_at_mut(r);
        let (hidden_row, rest) = rest.split_at_mut(h);
        let (mean, rest) = rest.split_at_mut(d);
        let (scale, rest) = rest.split_at_mut(d * d);
        let (noise, action) = rest.split_at_mut(d);
        /// Where the chosen expert's raw outputs come from.
        enum Source<'a> {
            /// The shared trunk's last hidden features and its output layer.
            Trunk(MatRef<'a, f32>, &'a vdd_nn::Linear),
            /// One network per expert.
            Nets(&'a mut [ResidualMlp]),
        }
        let mut source = match &mut experts.0 {
            ExpertNets::Shared(net) => {
                let (hidden, layer) = net.forward_hidden(states);
                Source::Trunk(hidden, layer)
            }
            ExpertNets::Separate(nets) => Source::Nets(nets),
        };
        for b in 0..states.nrows() {
            let lg = &out.log_gating[b * z..(b + 1) * z];
            let e = if held[b].left > 0 {
                held[b].left -= 1;
                held[b].expert
            } else {
                let e = if act_mode.greedy_gating {
                    (0..z).fold(0, |best, k| if lg[k] > lg[best] { k } else { best })
                } else {
                    let u: f32 = rng.random();
                    let mut acc = 0.0;
                    let mut pick = z - 1;
                    for (k, l) in lg.iter().enumerate() {
                        acc += l.exp();
                        if u < acc {
                            pick = k;
                            break;
                        }
                    }
                    pick
                };
                held[b] = Hold { expert: e, left: act_mode.hold_steps.saturating_sub(1) };
                e
            };
            last_experts.push(e);
            match &mut source {
                // The kernel the output layer's full forward pass uses on this many rows (a
                // row kernel for one, a matrix product for more), so the same bits.
                Source::Trunk(hidden, layer) if hidden.nrows() == 1 => {
                    for (j, v) in hidden_row.iter_mut().enumerate() {
                        *v = hidden[(0, j)];
                    }
                    layer.forward_row_cols(hidden_row, e * r..(e + 1) * r, raw);
                }
                Source::Trunk(hidden, layer) => {
                    raw.copy_from_slice(&layer.bias.value[e * r..(e + 1) * r]);
                    vdd_nn::matmul(
                        faer::MatMut::from_row_major_slice_mut(raw, 1, r),
                        faer::Accum::Add,
                        hidden.subrows(b, 1),
                        layer.weight_t().subcols(e * r, r),
                        1.0,
                    );
                }
                Source::Nets(nets) => {
                    let y = nets[e].forward_inference(states.subrows(b, 1));
                    for (c, v) in raw.iter_mut().enumerate() {
                        *v = y[(0, c)];
                    }
                }
            }
            expert.decode(raw, mean, scale);
            if act_mode.sample_action {
                vdd_core::fill_standard_normal(rng, noise);
                gaussian::sample_into(mean, scale, noise, action);
            } else {
                action.copy_from_slice(mean);
            }
            if let Some(norm) = action_normalizer.as_ref() {
                norm.denormalize(action);
            }
            // Weights are finite and bounded, but a deep network can still overflow: an error,
            // never a non-finite action.
            vdd_core::check_finite_slice("actions", action)?;
            for (j, &a) in action.iter().enumerate() {
                actions[(b, j)] = a;
            }
        }
        Ok(())
    }

    /// Both forward passes on observations (normalised here): for the likelihood.
    pub(super) fn forward_observations(&mut self, obs: MatRef<'_, f32>) -> vdd_core::Result<()> {
        self.on_observations(obs, |moe, states| moe.forward(states).map_err(to_core))
    }

    fn load_normalized_states(&mut self, obs: MatRef<'_, f32>) {
        let (n, ds) = (obs.nrows(), self.config.state_dim);
        if self.states.nrows() != n || self.states.ncols() != ds {
            self.states = Mat::zeros(n, ds);
        }
        self.states.copy_from(obs);
        if let Some(norm) = &self.obs_normalizer {
            for j in 0..ds {
                let (o, s) = (norm.offset[j], norm.scale[j]);
                for v in self.states.col_as_slice_mut(j) {
                    *v = (*v - o) / s;
                }
            }
        }
    }

    fn log_det_action_scale(&self) -> f32 {
        self.action_normalizer.as_ref().map_or(0.0, |a| a.scale.iter().map(|s| s.ln()).sum())
    }
}

/// A mixture error as the [`Policy`] trait's error: core errors stay what they are, the
/// others become [`CoreError::Implementor`] with the mixture error as the source.
fn to_core(e: MoeError) -> CoreError {
    match e {
        MoeError::Core(c) => c,
        other => CoreError::implementor(other),
    }
}
