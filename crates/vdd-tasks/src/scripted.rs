//! Scripted demonstrators as policies: [`Scripted`] holds what every task's demonstrator
//! shares (one plan per environment of a lockstep batch, drawn from the demonstrator's own
//! seeded stream, and the [`Policy`] checks), and a [`Script`] says what one task's plans are
//! and how a plan acts. Avoiding's demonstrator and Block-Push's oracle are `Scripted` scripts;
//! [`collect`] runs one into [`Demonstrations`].

use faer::reborrow::Reborrow;
use faer::{Mat, MatMut, MatRef};
use vdd_core::{CoreError, Policy, Rng, Seeds, check_act_args, check_finite, check_shape};

use crate::TaskError;
use crate::episodes::{Env, Rollout, Worker};

/// One task's scripted behaviour: how an episode's plan starts and how it acts.
pub trait Script: Clone {
    /// One episode's plan and progress.
    type Plan: Clone + std::fmt::Debug;
    /// The observation's length.
    const OBS_DIM: usize;
    /// The action's length.
    const ACTION_DIM: usize;
    /// The name of the demonstrator's seeded stream (`Seeds::new(seed).stream(STREAM)`).
    const STREAM: &'static str;
    /// The plan of an episode whose first observation is `obs`, drawing from `rng`.
    fn start(&self, obs: &[f32], rng: &mut Rng) -> Result<Self::Plan, CoreError>;
    /// Writes the action of `plan` at observation `obs` into `action`, advancing the plan.
    fn act(&self, plan: &mut Self::Plan, rng: &mut Rng, obs: &[f32], action: &mut [f32]);
}

/// A scripted demonstrator: a [`Policy`] that keeps one plan per environment between
/// [`Policy::reset`]s. [`Policy::act_into`] drives a single environment; [`Policy::act_batch`]
/// drives one environment per row (row `i` must stay the same environment until the next
/// reset, as lockstep rollouts guarantee; another batch size is an error). Plans start at an
/// episode's first action, in row order, from the demonstrator's own stream, which
/// [`Policy::seed`] resets.
#[derive(Debug, Clone)]
pub struct Scripted<S: Script> {
    script: S,
    rng: Rng,
    plans: Vec<S::Plan>,
    /// One observation row, reused.
    row: Vec<f32>,
    /// One action, reused.
    action: Vec<f32>,
}

impl<S: Script> Scripted<S> {
    /// A demonstrator running `script`, seeded with 0.
    pub fn with_script(script: S) -> Self {
        let (row, action) = (vec![0.0; S::OBS_DIM], vec![0.0; S::ACTION_DIM]);
        Self { script, rng: Self::stream(0), plans: Vec::new(), row, action }
    }

    /// The script.
    pub fn script(&self) -> &S {
        &self.script
    }

    /// The plan of environment (row) `row` of the current episode, once it has acted.
    pub fn plan(&self, row: usize) -> Option<&S::Plan> {
        self.plans.get(row)
    }

    fn stream(seed: u64) -> Rng {
        Seeds::new(seed).stream(S::STREAM)
    }

    /// Starts the plans of a batch of `obs.nrows()` environments at their first action.
    fn ensure_plans(&mut self, obs: MatRef<'_, f32>) -> Result<(), CoreError> {
        let n = obs.nrows();
        if self.plans.is_empty() {
            for i in 0..n {
                self.row.iter_mut().enumerate().for_each(|(j, r)| *r = obs[(i, j)]);
                let plan = self.script.start(&self.row, &mut self.rng)?;
                self.plans.push(plan);
            }
        } else if self.plans.len() != n {
            let (driving, got) = (self.plans.len(), n);
            return Err(CoreError::implementor(TaskError::DemonstratorBatch { driving, got }));
        }
        Ok(())
    }
}

impl<S: Script> Policy for Scripted<S> {
    fn obs_dim(&self) -> usize {
        S::OBS_DIM
    }

    fn action_dim(&self) -> usize {
        S::ACTION_DIM
    }

    fn reset(&mut self) {
        self.plans.clear();
    }

    fn seed(&mut self, seed: u64) {
        self.rng = Self::stream(seed);
    }

    fn act_into(&mut self, obs: &[f32], action: &mut [f32]) -> Result<(), CoreError> {
        check_act_args(self, obs, action)?;
        self.ensure_plans(MatRef::from_row_major_slice(obs, 1, S::OBS_DIM))?;
        self.script.act(&mut self.plans[0], &mut self.rng, obs, action);
        Ok(())
    }

    fn act_batch(
        &mut self,
        obs: MatRef<'_, f32>,
        mut actions: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        let n = obs.nrows();
        check_shape("observations", obs, n, S::OBS_DIM)?;
        check_shape("actions", actions.rb(), n, S::ACTION_DIM)?;
        check_finite("observations", obs)?;
        if n == 0 {
            return Ok(());
        }
        self.ensure_plans(obs)?;
        for (i, plan) in self.plans.iter_mut().enumerate() {
            self.row.iter_mut().enumerate().for_each(|(j, r)| *r = obs[(i, j)]);
            self.script.act(plan, &mut self.rng, &self.row, &mut self.action);
            self.action.iter().enumerate().for_each(|(j, &a)| actions[(i, j)] = a);
        }
        Ok(())
    }
}

/// A task's behaviour mode, as demonstrations count them.
pub trait Mode: Copy {
    /// How many modes the task has.
    const COUNT: usize;
    /// Its index in `0..COUNT`.
    fn index(&self) -> usize;
}

/// Demonstrations: one `T x OBS_DIM` observation and `T x ACTION_DIM` action matrix per
/// successful episode, and the mode each reached.
#[derive(Debug, Clone, PartialEq)]
pub struct Demonstrations<M> {
    /// Per-episode observations (the task's observation layout).
    pub observations: Vec<Mat<f32>>,
    /// Per-episode actions (as the task applied them, after its clipping).
    pub actions: Vec<Mat<f32>>,
    /// The behaviour mode each episode reached.
    pub modes: Vec<M>,
    /// Episodes run, including failures that were discarded.
    pub episodes_run: usize,
}

impl<M: Mode> Demonstrations<M> {
    /// Steps of each episode.
    pub fn lengths(&self) -> Vec<usize> {
        self.observations.iter().map(|o| o.nrows()).collect()
    }

    /// Episodes per behaviour mode, indexed by [`Mode::index`].
    pub fn mode_counts(&self) -> Vec<usize> {
        let mut counts = vec![0usize; M::COUNT];
        for m in &self.modes {
            counts[m.index()] += 1;
        }
        counts
    }

    /// Share of the episodes run that succeeded (and were kept).
    pub fn success_rate(&self) -> f64 {
        self.modes.len() as f64 / self.episodes_run.max(1) as f64
    }

    /// The demonstrations as a dataset (`vdd_data::Episodes`), ready to save as `.npz`.
    pub fn to_episodes(&self) -> Result<vdd_data::Episodes, vdd_data::DataError> {
        vdd_data::Episodes::from_episodes(self.observations.clone(), self.actions.clone())
    }
}

/// Runs `demonstrator` in environments of `E` built from `env` until `n` episodes have
/// succeeded and returns them (failed episodes are skipped; [`Demonstrations::success_rate`] reports how many).
/// Episode `i` runs with the policy seed and start seed `seeds(i)`, and `kept(rollout)` gives
/// the mode of a successful episode (`None`: a failure). More than `2n + 16` episodes without
/// `n` successes is an error; so is `n = 0`, or `n` episodes of `max_steps` steps that would
/// not fit in memory.
pub fn collect<E: Env, P: Policy + ?Sized, M: Mode>(
    demonstrator: &mut P,
    env: E::Config,
    (n, max_steps): (usize, usize),
    seeds: impl Fn(usize) -> (u64, u64),
    kept: impl Fn(&Rollout<E>) -> Option<M>,
) -> crate::Result<Demonstrations<M>> {
    if n == 0 {
        return Err(TaskError::InvalidArgument("cannot generate 0 demonstrations".into()));
    }
    let step = demonstrator.obs_dim() + demonstrator.action_dim();
    let per_episode = vdd_core::memory::product(&[max_steps, step, 4]) + 128;
    let bytes = (n as u64).saturating_mul(per_episode);
    vdd_core::memory::check_fits(&format!("{n} demonstrations"), bytes)?;
    let mut out = Demonstrations {
        observations: Vec::with_capacity(n),
        actions: Vec::with_capacity(n),
        modes: Vec::with_capacity(n),
        episodes_run: 0,
    };
    let mut worker = Worker::<E>::new(env);
    let max_attempts = 2 * n + 16;
    while out.observations.len() < n {
        if out.episodes_run == max_attempts {
            return Err(TaskError::TooManyFailures {
                collected: out.observations.len(),
                wanted: n,
                attempts: max_attempts,
            });
        }
        let i = out.episodes_run;
        let r = worker.episode(demonstrator, i, seeds(i), true)?;
        out.episodes_run += 1;
        if let Some(mode) = kept(&r) {
            if let Some(tr) = r.trajectory {
                out.observations.push(tr.observations);
                out.actions.push(tr.actions);
                out.modes.push(mode);
            }
        }
    }
    Ok(out)
}
