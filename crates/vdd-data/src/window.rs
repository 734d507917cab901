//! Observation windows and action chunks, as BESO and D3IL sample them.
//!
//! # Convention
//!
//! With an observation window of `W = obs_window` steps and an action chunk of
//! `C = action_chunk` steps, the sample anchored at step `t` of an episode is
//!
//! * state: `obs[t-W+1], obs[t-W+2], ..., obs[t]` concatenated, oldest first
//!   (length `W · d_obs`; entry `w · d_obs + j` is dimension `j` of `obs[t-W+1+w]`);
//! * action: `act[t], act[t+1], ..., act[t+C-1]` concatenated (length `C · d_act`).
//!
//! Only windows lying fully inside the episode's valid steps are used: `W-1 <= t <= T_i - C`,
//! so an episode yields `max(0, T_i - W - C + 2)` samples. This is D3IL's slicing (a slice of
//! `W + C - 1` steps, the first `W` observations and the last `C` actions). With
//! [`WindowConfig::pad_start`] the window may also start before the episode, the missing
//! observations repeating `obs[0]` (as BESO pads the first steps): then `0 <= t <= T_i - C` and
//! the episode yields `max(0, T_i - C + 1)` samples. Actions are never padded.
//!
//! Samples are numbered episode by episode, `t` increasing.
//!
//! # Acting
//!
//! A policy trained on such samples predicts from a window and returns a chunk. [`Windowed`]
//! turns it into a policy on raw observations, one action per step, by a [`DeploySpec`]
//! (feature map, `W`, `C`, and how many actions of each chunk to execute): it keeps the last
//! `W` observations, repeating the first at the start of an episode as `pad_start` does.

use faer::{Mat, MatMut};
use serde::{Deserialize, Serialize};

mod deploy;

pub use deploy::{DeploySpec, Windowed};

use crate::batch::BatchSource;
use crate::episodes::Episodes;
use crate::error::{DataError, Result};

/// Lengths of the observation window and the action chunk.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct WindowConfig {
    /// Observation steps per state, `W >= 1` (the current one and `W - 1` before it).
    pub obs_window: usize,
    /// Action steps per target, `C >= 1` (the current one and `C - 1` after it).
    pub action_chunk: usize,
    /// Also sample the first `W - 1` steps of every episode, padding the window by repeating
    /// the episode's first observation.
    pub pad_start: bool,
}

impl WindowConfig {
    /// Window `obs_window`, chunk `action_chunk`, no start padding.
    pub const fn new(obs_window: usize, action_chunk: usize) -> Self {
        Self { obs_window, action_chunk, pad_start: false }
    }

    /// One observation, one action: plain `(state, action)` pairs.
    pub const fn single_step() -> Self {
        Self::new(1, 1)
    }

    /// The same window with start padding switched on or off.
    pub const fn with_pad_start(mut self, pad_start: bool) -> Self {
        self.pad_start = pad_start;
        self
    }

    /// Valid steps one sample needs: `W + C - 1`, or `C` with start padding.
    pub const fn steps_needed(&self) -> usize {
        if self.pad_start { self.action_chunk } else { self.obs_window + self.action_chunk - 1 }
    }
}

/// Position of one sample: episode index and anchor step `t`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SamplePosition {
    /// Episode index.
    pub episode: usize,
    /// Anchor step: the last observation of the window and the first action of the chunk.
    pub t: usize,
}

/// Windowed samples of a set of episodes (see the [module docs](self) for the convention).
///
/// ```
/// use faer::Mat;
/// use vdd_data::{Episodes, SequenceDataset, WindowConfig};
/// // One episode of 5 steps; observation t is [t], action t is [10 t].
/// let obs = vec![Mat::from_fn(5, 1, |t, _| t as f32)];
/// let act = vec![Mat::from_fn(5, 1, |t, _| 10.0 * t as f32)];
/// let episodes = Episodes::from_episodes(obs, act).unwrap();
/// let data = SequenceDataset::new(episodes, WindowConfig::new(2, 3)).unwrap();
/// assert_eq!(data.len(), 2); // anchors t = 1 and t = 2
/// let (states, actions) = data.to_matrices();
/// assert_eq!((states[(0, 0)], states[(0, 1)]), (0.0, 1.0)); // obs[0], obs[1]
/// assert_eq!((actions[(1, 0)], actions[(1, 2)]), (20.0, 40.0)); // act[2] .. act[4]
/// ```
#[derive(Debug, Clone, PartialEq)]
pub struct SequenceDataset {
    episodes: Episodes,
    config: WindowConfig,
    samples: Vec<SamplePosition>,
    skipped: usize,
}

impl SequenceDataset {
    /// Indexes every window of `episodes` that `config` allows. Episodes too short for one
    /// window are skipped (see [`SequenceDataset::skipped_episodes`]).
    ///
    /// Errors: [`DataError::Config`] for a zero window or chunk; [`DataError::WindowTooLong`]
    /// when no episode is long enough.
    pub fn new(episodes: Episodes, config: WindowConfig) -> Result<Self> {
        if config.obs_window == 0 || config.action_chunk == 0 {
            return Err(DataError::Config(format!(
                "observation window and action chunk must be at least 1, got {} and {}",
                config.obs_window, config.action_chunk
            )));
        }
        let needed = config.steps_needed();
        let first_t = if config.pad_start { 0 } else { config.obs_window - 1 };
        let mut samples = Vec::new();
        let mut skipped = 0;
        for (episode, &len) in episodes.lengths().iter().enumerate() {
            if len < needed {
                skipped += 1;
                continue;
            }
            samples.extend(
                (first_t..=len - config.action_chunk).map(|t| SamplePosition { episode, t }),
            );
        }
        if samples.is_empty() {
            return Err(DataError::WindowTooLong {
                obs_window: config.obs_window,
                action_chunk: config.action_chunk,
                needed,
                longest: episodes.lengths().iter().copied().max().unwrap_or(0),
            });
        }
        Ok(Self { episodes, config, samples, skipped })
    }

    /// Number of samples (at least 1).
    pub fn len(&self) -> usize {
        self.samples.len()
    }

    /// Always `false`: construction fails rather than produce an empty dataset.
    pub fn is_empty(&self) -> bool {
        self.samples.is_empty()
    }

    /// The window configuration.
    pub fn config(&self) -> WindowConfig {
        self.config
    }

    /// The underlying episodes.
    pub fn episodes(&self) -> &Episodes {
        &self.episodes
    }

    /// Number of episodes too short to yield any sample.
    pub fn skipped_episodes(&self) -> usize {
        self.skipped
    }

    /// Length of a flattened state, `W · d_obs`.
    pub fn state_dim(&self) -> usize {
        self.config.obs_window * self.episodes.obs_dim()
    }

    /// Length of a flattened action chunk, `C · d_act`.
    pub fn action_dim(&self) -> usize {
        self.config.action_chunk * self.episodes.act_dim()
    }

    /// Episode and anchor step of sample `k`, or `None` past the end.
    pub fn position(&self, k: usize) -> Option<SamplePosition> {
        self.samples.get(k).copied()
    }

    /// Writes sample `k` into `state` (length [`state_dim`](Self::state_dim)) and `action`
    /// (length [`action_dim`](Self::action_dim)).
    ///
    /// Errors: [`DataError::Config`] for `k` out of range, [`DataError::Shape`] for buffers of
    /// the wrong length.
    pub fn fill_sample(&self, k: usize, state: &mut [f32], action: &mut [f32]) -> Result<()> {
        if k >= self.len() {
            return Err(DataError::Config(format!(
                "sample {k} out of range for {} samples",
                self.len()
            )));
        }
        for (what, got, want) in [
            ("state buffer", state.len(), self.state_dim()),
            ("action buffer", action.len(), self.action_dim()),
        ] {
            if got != want {
                return Err(DataError::Shape {
                    what: what.into(),
                    expected: format!("length {want}"),
                    got: format!("length {got}"),
                });
            }
        }
        let d_obs = self.episodes.obs_dim();
        let d_act = self.episodes.act_dim();
        self.for_each_step(
            k,
            |w, o| state[w * d_obs..(w + 1) * d_obs].copy_from_slice(o),
            |c, a| action[c * d_act..(c + 1) * d_act].copy_from_slice(a),
        );
        Ok(())
    }

    /// Every sample as two matrices with one row per sample (`len() x state_dim()` and
    /// `len() x action_dim()`), in sample order.
    pub fn to_matrices(&self) -> (Mat<f32>, Mat<f32>) {
        let mut states = Mat::<f32>::zeros(self.len(), self.state_dim());
        let mut actions = Mat::<f32>::zeros(self.len(), self.action_dim());
        for k in 0..self.len() {
            self.write_row(k, k, states.as_mut(), actions.as_mut());
        }
        (states, actions)
    }

    /// Calls `obs(w, observation)` for the `W` window steps and `act(c, action)` for the `C`
    /// chunk steps of sample `k`.
    #[inline]
    fn for_each_step(
        &self,
        k: usize,
        mut obs: impl FnMut(usize, &[f32]),
        mut act: impl FnMut(usize, &[f32]),
    ) {
        let SamplePosition { episode, t } = self.samples[k];
        let w_len = self.config.obs_window;
        for w in 0..w_len {
            // Step t - W + 1 + w, clamped at 0 (only reachable with start padding).
            let s = (t + w + 1).saturating_sub(w_len);
            obs(w, self.episodes.step_observation(episode, s));
        }
        for c in 0..self.config.action_chunk {
            act(c, self.episodes.step_action(episode, t + c));
        }
    }
}

impl BatchSource for SequenceDataset {
    fn num_samples(&self) -> usize {
        self.len()
    }

    fn state_dim(&self) -> usize {
        SequenceDataset::state_dim(self)
    }

    fn action_dim(&self) -> usize {
        SequenceDataset::action_dim(self)
    }

    fn write_row(
        &self,
        sample: usize,
        row: usize,
        mut states: MatMut<'_, f32>,
        mut actions: MatMut<'_, f32>,
    ) {
        let d_obs = self.episodes.obs_dim();
        let d_act = self.episodes.act_dim();
        self.for_each_step(
            sample,
            |w, o| {
                for (j, &v) in o.iter().enumerate() {
                    states[(row, w * d_obs + j)] = v;
                }
            },
            |c, a| {
                for (j, &v) in a.iter().enumerate() {
                    actions[(row, c * d_act + j)] = v;
                }
            },
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::episodes::tests::ramp_episodes;

    #[test]
    fn windows_follow_the_documented_convention() {
        // Lengths 3, 4, 5, 6, 3; obs (i, t, j) = 100 i + 10 t + j, act = -(100 i + 10 t + j).
        let e = ramp_episodes(5, 2, 1);
        let data = SequenceDataset::new(e, WindowConfig::new(2, 3)).unwrap();
        // Per episode max(0, T - 2 - 3 + 2) = T - 3: 0, 1, 2, 3, 0.
        assert_eq!(data.len(), 6);
        assert_eq!(data.skipped_episodes(), 2);
        assert_eq!((data.state_dim(), data.action_dim()), (4, 3));
        let anchors: Vec<(usize, usize)> =
            (0..6).map(|k| data.position(k).map(|p| (p.episode, p.t)).unwrap()).collect();
        assert_eq!(anchors, vec![(1, 1), (2, 1), (2, 2), (3, 1), (3, 2), (3, 3)]);
        assert_eq!(data.position(6), None);
        let mut s = [0.0f32; 4];
        let mut a = [0.0f32; 3];
        data.fill_sample(4, &mut s, &mut a).unwrap(); // episode 3, t = 2
        assert_eq!(s, [310.0, 311.0, 320.0, 321.0]);
        assert_eq!(a, [-320.0, -330.0, -340.0]);
        let (sm, am) = data.to_matrices();
        for j in 0..4 {
            assert_eq!(sm[(4, j)], s[j]);
        }
        for j in 0..3 {
            assert_eq!(am[(4, j)], a[j]);
        }
        // The last sample's chunk ends exactly at the last valid step (T = 6: act[3..6]).
        assert_eq!(am[(5, 2)], -350.0);
    }

    #[test]
    fn pad_start_repeats_the_first_observation() {
        let e = ramp_episodes(1, 1, 1); // one episode of 3 steps
        let data = SequenceDataset::new(e, WindowConfig::new(3, 2).with_pad_start(true)).unwrap();
        assert_eq!(data.len(), 2); // t = 0, 1
        let (s, a) = data.to_matrices();
        assert_eq!((s[(0, 0)], s[(0, 1)], s[(0, 2)]), (0.0, 0.0, 0.0));
        assert_eq!((s[(1, 0)], s[(1, 1)], s[(1, 2)]), (0.0, 0.0, 10.0));
        assert_eq!((a[(0, 0)], a[(0, 1)], a[(1, 1)]), (-0.0, -10.0, -20.0));
    }

    #[test]
    fn sample_counts_match_the_formula() {
        let e = ramp_episodes(9, 1, 1); // lengths 3..=6
        for w in 1..5 {
            for c in 1..5 {
                for pad in [false, true] {
                    let cfg = WindowConfig::new(w, c).with_pad_start(pad);
                    let want: usize = e
                        .lengths()
                        .iter()
                        .map(|&t| (t + 1).saturating_sub(cfg.steps_needed()))
                        .sum();
                    match SequenceDataset::new(e.clone(), cfg) {
                        Ok(d) => assert_eq!(d.len(), want, "{cfg:?}"),
                        Err(DataError::WindowTooLong { needed, longest, .. }) => {
                            assert_eq!(want, 0);
                            assert_eq!((needed, longest), (cfg.steps_needed(), 6));
                        }
                        Err(err) => panic!("{err}"),
                    }
                }
            }
        }
    }

    #[test]
    fn bad_windows_are_rejected() {
        let e = ramp_episodes(3, 1, 1); // longest 5
        assert!(matches!(
            SequenceDataset::new(e.clone(), WindowConfig::new(3, 4)),
            Err(DataError::WindowTooLong { needed: 6, longest: 5, .. })
        ));
        assert!(matches!(
            SequenceDataset::new(e.clone(), WindowConfig::new(0, 1)),
            Err(DataError::Config(_))
        ));
        assert!(matches!(
            SequenceDataset::new(e.clone(), WindowConfig::new(1, 0)),
            Err(DataError::Config(_))
        ));
        let data = SequenceDataset::new(e, WindowConfig::new(2, 2)).unwrap();
        let mut s = [0.0f32; 2];
        let mut a = [0.0f32; 2];
        assert!(matches!(data.fill_sample(99, &mut s, &mut a), Err(DataError::Config(_))));
        assert!(matches!(data.fill_sample(0, &mut s[..1], &mut a), Err(DataError::Shape { .. })));
        assert!(matches!(data.fill_sample(0, &mut s, &mut [0.0; 3]), Err(DataError::Shape { .. })));
    }

    #[test]
    fn single_step_windows_equal_episode_matrices() {
        let e = ramp_episodes(4, 3, 2);
        let data = SequenceDataset::new(e.clone(), WindowConfig::single_step()).unwrap();
        assert_eq!(data.to_matrices(), e.to_matrices());
    }
}
