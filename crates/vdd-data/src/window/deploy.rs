//! The acting side of the window convention: [`DeploySpec`] says how a policy trained on
//! featured, windowed samples meets raw observations, and [`Windowed`] runs it that way.

use faer::reborrow::ReborrowMut;
use faer::{Mat, MatMut, MatRef};
use serde::{Deserialize, Serialize};
use vdd_core::{CoreError, Policy, check_act_args, check_shape};

use crate::error::{DataError, Result};
use crate::features::{self, FeatureMap, FeatureMapId};

/// How a policy trained on samples of this crate's convention acts on raw observations: the
/// feature map applied to each raw observation, the observation window `W`, the action chunk
/// `C` and the actions of each chunk executed before predicting again, from index
/// `chunk_start` of the chunk (`chunk_start < C`, `1 ≤ execute_steps ≤ C − chunk_start`).
///
/// A model saved with its spec needs nothing else to act in its environment (`vdd-moe` saves
/// one in every mixture file; [`Windowed`] applies it).
///
/// ```
/// use vdd_data::DeploySpec;
/// use vdd_data::features::POSITION_AND_LAG;
///
/// let spec = DeploySpec { obs_window: 2, action_chunk: 4, execute_steps: 2, ..DeploySpec::identity() }
///     .with_features(POSITION_AND_LAG);
/// spec.validate()?;
/// // A policy of this spec sees 2 featured 4-D observations and predicts 4 2-D actions.
/// spec.check_policy_dims(8, 8)?;
/// assert_eq!(spec.raw_dims(8, 8)?, (4, 2));
///
/// let bad = DeploySpec { execute_steps: 5, ..spec };
/// assert_eq!(
///     bad.validate().unwrap_err().to_string(),
///     "`execute_steps` = 5: must be between 1 and action_chunk = 4"
/// );
/// # Ok::<(), vdd_data::DataError>(())
/// ```
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DeploySpec {
    /// The feature map applied to every raw observation ([`crate::features`]).
    pub features: FeatureMapId,
    /// Observation window `W`: the policy sees the last `W` (featured) observations, oldest
    /// first, the first one repeated at the start of an episode.
    pub obs_window: usize,
    /// Action chunk `C`: the policy predicts `C` actions at once.
    pub action_chunk: usize,
    /// Actions of each chunk executed before the policy is asked again
    /// (`1..=C − chunk_start`).
    pub execute_steps: usize,
    /// Index in the chunk of the first executed action (`0..C`; 0 unless set). A chunk that
    /// also predicts the steps of the observation window before the current one, as LeRobot's
    /// and diffusion_policy's chunks do (they execute from `n_obs_steps − 1`), starts there.
    /// Absent from saved specs when 0, so files of earlier versions read as before.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub chunk_start: usize,
}

fn is_zero(x: &usize) -> bool {
    *x == 0
}

impl Default for DeploySpec {
    /// [`DeploySpec::identity`].
    fn default() -> Self {
        Self::identity()
    }
}

impl DeploySpec {
    /// Raw observations in, one action out: the identity map, `W = C = 1`, executing 1. A
    /// model saved without a spec acts this way.
    pub fn identity() -> Self {
        Self {
            features: features::IDENTITY.id(),
            obs_window: 1,
            action_chunk: 1,
            execute_steps: 1,
            chunk_start: 0,
        }
    }

    /// The same spec with `map` as its feature map.
    pub fn with_features(mut self, map: FeatureMap) -> Self {
        self.features = map.id();
        self
    }

    /// Checks the ranges (`W ≥ 1`, `C ≥ 1`, `chunk_start < C`,
    /// `1 ≤ execute_steps ≤ C − chunk_start`) and that the feature map is registered; returns
    /// the map. Errors name the setting and its value.
    pub fn validate(&self) -> Result<FeatureMap> {
        let bad = |key, value: usize, reason: String| {
            Err(DataError::Spec { key, value: value.to_string(), reason })
        };
        if self.obs_window == 0 {
            return bad("obs_window", 0, "must be at least 1".into());
        }
        if self.action_chunk == 0 {
            return bad("action_chunk", 0, "must be at least 1".into());
        }
        if self.chunk_start >= self.action_chunk {
            let reason = format!("must be below action_chunk = {}", self.action_chunk);
            return bad("chunk_start", self.chunk_start, reason);
        }
        let room = self.action_chunk - self.chunk_start;
        if self.execute_steps == 0 || self.execute_steps > room {
            let reason = match self.chunk_start {
                0 => format!("must be between 1 and action_chunk = {}", self.action_chunk),
                s => format!(
                    "must be between 1 and action_chunk − chunk_start = {} − {s}",
                    self.action_chunk
                ),
            };
            return bad("execute_steps", self.execute_steps, reason);
        }
        self.features.resolve().map_err(|e| DataError::Spec {
            key: "features",
            value: self.features.to_string(),
            reason: e.to_string(),
        })
    }

    /// The raw observation and action dimensions of a policy of this spec whose own
    /// observation is `obs_dim` (a window of `W` featured observations) and action
    /// `action_dim` (a chunk of `C` actions); an error if they do not split into `W` and `C`
    /// parts or the feature map does not apply to the parts.
    pub fn raw_dims(&self, obs_dim: usize, action_dim: usize) -> Result<(usize, usize)> {
        let map = self.validate()?;
        let split = |key, parts: usize, dim: usize, what: &str| {
            if dim == 0 || dim % parts != 0 {
                Err(DataError::Spec {
                    key,
                    value: parts.to_string(),
                    reason: format!(
                        "the policy's {what} dimension {dim} is not a positive multiple of it"
                    ),
                })
            } else {
                Ok(dim / parts)
            }
        };
        let obs = split("obs_window", self.obs_window, obs_dim, "observation")?;
        let act = split("action_chunk", self.action_chunk, action_dim, "action")?;
        map.check_dim(obs)?;
        Ok((obs, act))
    }

    /// [`DeploySpec::raw_dims`] without the dimensions: whether the spec fits the policy.
    pub fn check_policy_dims(&self, obs_dim: usize, action_dim: usize) -> Result<()> {
        self.raw_dims(obs_dim, action_dim).map(|_| ())
    }
}

/// A policy trained on observation windows of `W` steps and action chunks of `C` steps (and on
/// featured observations) as a policy on raw observations that returns one action per step,
/// by a [`DeploySpec`]: each raw observation goes through the spec's feature map, the last `W`
/// of them (the first one repeated at the start of an episode, as
/// [`WindowConfig::pad_start`](crate::WindowConfig::pad_start) builds training windows) form
/// the inner policy's observation, and the first `execute_steps` actions of each predicted
/// chunk (from index [`DeploySpec::chunk_start`]) are returned one per step before the inner
/// policy is asked again.
///
/// State is kept per batch row, so lockstep evaluation (one `act_batch` per step, row `i`
/// always the same environment between `reset`s) works; `act_into` uses row 0. With the
/// identity map and `W = C = 1` it is a pass-through.
///
/// ```
/// use vdd_core::{CoreError, Policy};
/// use vdd_data::{DeploySpec, Windowed};
///
/// /// Sees two 1-D observations, predicts a chunk of three 1-D actions: (sum, 10, 20).
/// struct Chunker;
/// impl Policy for Chunker {
///     fn obs_dim(&self) -> usize { 2 }
///     fn action_dim(&self) -> usize { 3 }
///     fn act_into(&mut self, obs: &[f32], action: &mut [f32]) -> Result<(), CoreError> {
///         action.copy_from_slice(&[obs[0] + obs[1], 10.0, 20.0]);
///         Ok(())
///     }
/// }
/// let spec = DeploySpec { obs_window: 2, action_chunk: 3, execute_steps: 2, ..DeploySpec::identity() };
/// let mut policy = Windowed::new(Chunker, spec)?;
/// assert_eq!((policy.obs_dim(), policy.action_dim()), (1, 1));
/// assert_eq!(policy.act(&[1.0])?, [2.0]); // window [1, 1] (padded), first action of the chunk
/// assert_eq!(policy.act(&[5.0])?, [10.0]); // second action of the same chunk
/// assert_eq!(policy.act(&[7.0])?, [12.0]); // a new chunk from the window [5, 7]
/// # Ok::<(), Box<dyn std::error::Error>>(())
/// ```
#[derive(Debug, Clone)]
pub struct Windowed<P> {
    inner: P,
    spec: DeploySpec,
    features: FeatureMap,
    obs_dim: usize,
    act_dim: usize,
    rows: Vec<RowState>,
    batch_obs: Mat<f32>,
    batch_act: Mat<f32>,
    need: Vec<usize>,
}

#[derive(Debug, Clone, Default)]
struct RowState {
    /// The last `W` observations, oldest first (empty at episode start).
    history: Vec<f32>,
    /// The current chunk (`C · d_act`) and the next index to execute.
    chunk: Vec<f32>,
    next: usize,
}

impl<P: Policy> Windowed<P> {
    /// Wraps `inner`, whose observation is `W · obs_dim` and action `C · act_dim`, by `spec`
    /// (an error, naming the setting, if the spec is invalid or does not fit `inner`).
    pub fn new(inner: P, spec: DeploySpec) -> Result<Self> {
        let features = spec.validate()?;
        let (obs_dim, act_dim) = spec.raw_dims(inner.obs_dim(), inner.action_dim())?;
        Ok(Self {
            inner,
            spec,
            features,
            obs_dim,
            act_dim,
            rows: Vec::new(),
            batch_obs: Mat::zeros(0, 0),
            batch_act: Mat::zeros(0, 0),
            need: Vec::new(),
        })
    }

    /// The spec it acts by.
    pub fn spec(&self) -> &DeploySpec {
        &self.spec
    }

    /// The wrapped policy.
    pub fn inner(&self) -> &P {
        &self.inner
    }

    /// The wrapped policy, mutably (changing its dimensions breaks the wrapper).
    pub fn inner_mut(&mut self) -> &mut P {
        &mut self.inner
    }

    /// The wrapped policy.
    pub fn into_inner(self) -> P {
        self.inner
    }

    fn passthrough(&self) -> bool {
        self.spec.obs_window == 1 && self.spec.action_chunk == 1 && self.features.is_identity()
    }

    fn push_obs(&mut self, row: usize, obs: &mut [f32]) {
        self.features.apply(obs);
        let (w, d) = (self.spec.obs_window, self.obs_dim);
        let r = &mut self.rows[row];
        if r.history.is_empty() {
            r.history = obs.repeat(w);
        } else {
            r.history.copy_within(d.., 0);
            r.history[(w - 1) * d..].copy_from_slice(obs);
        }
    }
}

impl<P: Policy> Policy for Windowed<P> {
    fn obs_dim(&self) -> usize {
        self.obs_dim
    }
    fn action_dim(&self) -> usize {
        self.act_dim
    }
    fn reset(&mut self) {
        self.rows.clear();
        self.inner.reset();
    }
    fn seed(&mut self, seed: u64) {
        self.inner.seed(seed);
    }
    /// The inner policy's: the experts of its last prediction (with a chunk longer than one
    /// step, the chunk being executed).
    fn last_experts(&self) -> &[usize] {
        self.inner.last_experts()
    }
    fn act_into(&mut self, obs: &[f32], action: &mut [f32]) -> vdd_core::Result<()> {
        if self.passthrough() {
            return self.inner.act_into(obs, action);
        }
        check_act_args(self, obs, action)?;
        let o = MatRef::from_row_major_slice(obs, 1, obs.len());
        let a = MatMut::from_row_major_slice_mut(action, 1, self.act_dim);
        self.act_batch(o, a)
    }
    fn act_batch(
        &mut self,
        obs: MatRef<'_, f32>,
        mut actions: MatMut<'_, f32>,
    ) -> vdd_core::Result<()> {
        if self.passthrough() {
            return self.inner.act_batch(obs, actions);
        }
        let n = obs.nrows();
        check_shape("observations", obs, n, self.obs_dim)?;
        check_shape("actions", actions.rb_mut().as_ref(), n, self.act_dim)?;
        if self.rows.len() != n {
            self.rows = vec![RowState::default(); n];
        }
        let end = self.spec.chunk_start + self.spec.execute_steps;
        let mut o = vec![0.0f32; self.obs_dim];
        self.need.clear();
        for i in 0..n {
            for (j, x) in o.iter_mut().enumerate() {
                *x = obs[(i, j)];
            }
            if o.iter().any(|x| !x.is_finite()) {
                return Err(CoreError::NonFinite { what: "observation" });
            }
            self.push_obs(i, &mut o);
            let r = &self.rows[i];
            if r.chunk.is_empty() || r.next >= end {
                self.need.push(i);
            }
        }
        if !self.need.is_empty() {
            let (m, win_dim, chunk_dim) = (
                self.need.len(),
                self.spec.obs_window * self.obs_dim,
                self.spec.action_chunk * self.act_dim,
            );
            if self.batch_obs.nrows() != m {
                self.batch_obs = Mat::zeros(m, win_dim);
                self.batch_act = Mat::zeros(m, chunk_dim);
            }
            for (b, &i) in self.need.iter().enumerate() {
                for (j, x) in self.rows[i].history.iter().enumerate() {
                    self.batch_obs[(b, j)] = *x;
                }
            }
            self.inner.act_batch(self.batch_obs.as_ref(), self.batch_act.as_mut())?;
            for (b, &i) in self.need.iter().enumerate() {
                let r = &mut self.rows[i];
                r.chunk.clear();
                r.chunk.extend((0..chunk_dim).map(|j| self.batch_act[(b, j)]));
                r.next = self.spec.chunk_start;
            }
        }
        for i in 0..n {
            let r = &mut self.rows[i];
            let start = r.next * self.act_dim;
            for j in 0..self.act_dim {
                actions[(i, j)] = r.chunk[start + j];
            }
            r.next += 1;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::features::POSITION_AND_LAG;

    /// Observation window of 2 (4 numbers), chunk of 3 (action = [sum of window, call count, t]).
    #[derive(Debug, Clone)]
    struct Probe {
        calls: f32,
    }
    impl Policy for Probe {
        fn obs_dim(&self) -> usize {
            4
        }
        fn action_dim(&self) -> usize {
            3
        }
        fn reset(&mut self) {
            self.calls = 0.0;
        }
        fn act_into(&mut self, obs: &[f32], action: &mut [f32]) -> vdd_core::Result<()> {
            self.calls += 1.0;
            action[0] = obs[0] * 1000.0 + obs[2];
            action[1] = self.calls;
            action[2] = obs[1] * 1000.0 + obs[3];
            Ok(())
        }
    }

    fn spec(w: usize, c: usize, e: usize) -> DeploySpec {
        DeploySpec { obs_window: w, action_chunk: c, execute_steps: e, ..DeploySpec::identity() }
    }

    #[test]
    fn windows_pad_at_start_and_chunks_are_executed_in_order() {
        // obs_dim 2, act_dim 1; window 2, chunk 3, execute 2.
        let mut w = Windowed::new(Probe { calls: 0.0 }, spec(2, 3, 2)).unwrap();
        assert_eq!((w.obs_dim(), w.action_dim()), (2, 1));
        let a0 = w.act(&[1.0, 2.0]).unwrap(); // window [o0, o0] -> chunk [1001, 1, 2002]
        assert_eq!(a0, vec![1001.0]);
        let a1 = w.act(&[3.0, 4.0]).unwrap(); // second action of the chunk
        assert_eq!(a1, vec![1.0]);
        let a2 = w.act(&[5.0, 6.0]).unwrap(); // new chunk from window [o1, o2]
        assert_eq!(a2, vec![3005.0]);
        w.reset();
        let a = w.act(&[7.0, 8.0]).unwrap();
        assert_eq!(a, vec![7007.0], "reset clears the history");
        assert!(w.act(&[f32::NAN, 0.0]).is_err());
        assert!(w.act(&[1.0]).is_err());
    }

    #[test]
    fn chunks_are_executed_from_their_start_offset() {
        // Chunk [sum of window, call count, t]; execute 2 from index 1: the count, then t.
        let s = DeploySpec { chunk_start: 1, ..spec(2, 3, 2) };
        let mut w = Windowed::new(Probe { calls: 0.0 }, s).unwrap();
        assert_eq!(w.act(&[1.0, 2.0]).unwrap(), [1.0]); // first chunk, index 1: call count 1
        assert_eq!(w.act(&[3.0, 4.0]).unwrap(), [2002.0]); // index 2 of the same chunk
        assert_eq!(w.act(&[5.0, 6.0]).unwrap(), [2.0]); // a new chunk (call 2), index 1
        let one = DeploySpec { chunk_start: 2, ..spec(2, 3, 1) };
        let mut w = Windowed::new(Probe { calls: 0.0 }, one).unwrap();
        for (x, want) in [(1.0f32, 2002.0f32), (3.0, 2004.0), (5.0, 4006.0)] {
            assert_eq!(w.act(&[x, x + 1.0]).unwrap(), [want], "a new chunk every step");
        }
    }

    #[test]
    fn batched_rows_keep_their_own_state() {
        let mut w = Windowed::new(Probe { calls: 0.0 }, spec(2, 3, 3)).unwrap();
        let obs = faer::mat![[1.0f32, 0.0], [2.0, 0.0]];
        let mut act = Mat::<f32>::zeros(2, 1);
        w.act_batch(obs.as_ref(), act.as_mut()).unwrap();
        assert_eq!((act[(0, 0)], act[(1, 0)]), (1001.0, 2002.0));
        w.act_batch(obs.as_ref(), act.as_mut()).unwrap();
        assert_eq!((act[(0, 0)], act[(1, 0)]), (1.0, 2.0), "second chunk entry: call count");
    }

    /// Echoes its observation as the action.
    #[derive(Debug, Clone)]
    struct Echo(usize);
    impl Policy for Echo {
        fn obs_dim(&self) -> usize {
            self.0
        }
        fn action_dim(&self) -> usize {
            self.0
        }
        fn act_into(&mut self, obs: &[f32], action: &mut [f32]) -> vdd_core::Result<()> {
            action.copy_from_slice(obs);
            Ok(())
        }
    }

    #[test]
    fn features_are_applied_to_every_observation_before_the_policy() {
        let mut w = Windowed::new(Echo(4), spec(1, 1, 1).with_features(POSITION_AND_LAG)).unwrap();
        let mut a = [0.0f32; 4];
        for x in [1.0f32, 2.0] {
            w.act_into(&[x, 0.5, 0.25, 0.0], &mut a).unwrap();
            assert_eq!(a, [0.25, 0.0, x - 0.25, 0.5]);
        }
        let obs = faer::mat![[1.0f32, 0.5, 0.25, 0.0], [3.0, 2.0, 1.0, 0.0]];
        let mut act = Mat::<f32>::zeros(2, 4);
        w.act_batch(obs.as_ref(), act.as_mut()).unwrap();
        assert_eq!(act, faer::mat![[0.25f32, 0.0, 0.75, 0.5], [1.0, 0.0, 2.0, 2.0]]);
        // The identity with W = C = 1 passes straight through.
        let mut p = Windowed::new(Echo(3), DeploySpec::identity()).unwrap();
        assert!(p.passthrough());
        assert_eq!(p.act(&[1.0, 2.0, 3.0]).unwrap(), [1.0, 2.0, 3.0]);
        assert_eq!(p.spec(), &DeploySpec::identity());
        assert_eq!(p.into_inner().0, 3);
    }

    #[test]
    fn bad_specs_name_the_setting_and_its_value() {
        let cases = [
            (spec(0, 1, 1), "`obs_window` = 0: must be at least 1"),
            (spec(1, 0, 1), "`action_chunk` = 0: must be at least 1"),
            (spec(1, 3, 0), "`execute_steps` = 0: must be between 1 and action_chunk = 3"),
            (spec(2, 3, 4), "`execute_steps` = 4: must be between 1 and action_chunk = 3"),
            (
                DeploySpec { chunk_start: 3, ..spec(2, 3, 1) },
                "`chunk_start` = 3: must be below action_chunk = 3",
            ),
            (
                DeploySpec { chunk_start: 1, ..spec(2, 3, 3) },
                "`execute_steps` = 3: must be between 1 and action_chunk − chunk_start = 3 − 1",
            ),
            (spec(3, 3, 1), "`obs_window` = 3: the policy's observation dimension 4"),
            (spec(2, 2, 1), "`action_chunk` = 2: the policy's action dimension 3"),
            (
                DeploySpec { features: FeatureMapId::new("lag", 1), ..spec(2, 3, 1) },
                "`features` = lag v1: unknown feature map `lag` version 1 (known: identity v1, \
                 position_and_lag v1)",
            ),
            (
                DeploySpec { features: FeatureMapId::new("identity", 2), ..spec(2, 3, 1) },
                "`features` = identity v2: unknown feature map",
            ),
        ];
        for (s, want) in cases {
            let e = Windowed::new(Probe { calls: 0.0 }, s.clone()).unwrap_err();
            assert!(e.to_string().starts_with(want), "{s:?}: {e}");
        }
        // Position and lag needs even observations: Probe's window of 4 in 4 parts has 1 entry.
        let s = spec(4, 3, 1).with_features(POSITION_AND_LAG);
        let e = Windowed::new(Probe { calls: 0.0 }, s).unwrap_err();
        assert!(e.to_string().starts_with("`features` = position_and_lag v1: needs"), "{e}");
    }

    #[test]
    fn specs_serialise_with_named_settings_and_refuse_unknown_ones() {
        let s = spec(2, 4, 3).with_features(POSITION_AND_LAG);
        let json = serde_json::to_string(&s).unwrap();
        assert_eq!(
            json,
            r#"{"features":{"name":"position_and_lag","version":1},"obs_window":2,"action_chunk":4,"execute_steps":3}"#
        );
        assert_eq!(serde_json::from_str::<DeploySpec>(&json).unwrap(), s);
        let extra = json.replace("\"obs_window\"", "\"window\":1,\"obs_window\"");
        assert!(serde_json::from_str::<DeploySpec>(&extra).is_err());
        assert_eq!(DeploySpec::default(), DeploySpec::identity());
        // A start offset is saved when set, and read back; hostile offsets fail validation.
        let offset = DeploySpec { chunk_start: 1, ..spec(2, 4, 3) };
        let json = serde_json::to_string(&offset).unwrap();
        assert!(json.ends_with(r#""execute_steps":3,"chunk_start":1}"#), "{json}");
        let back: DeploySpec = serde_json::from_str(&json).unwrap();
        assert_eq!(back, offset);
        back.validate().unwrap();
        for bad in [r#""chunk_start":4"#, r#""chunk_start":2"#] {
            let s: DeploySpec =
                serde_json::from_str(&json.replace(r#""chunk_start":1"#, bad)).unwrap();
            assert!(s.validate().is_err(), "{bad}");
        }
    }
}
