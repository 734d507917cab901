//! Scripted demonstrators as policies: [`Scripted`] holds what every task's demonstrator
//! shares (one plan per environment of a lockstep batch, drawn from the demonstrator's own
//! seeded stream, and the [`Policy`] checks), and a [`Script`] says what one task's plans are
//! and how a plan acts. Avoiding's demonstrator and Block-Push's oracle are `Scripted` scripts.

use faer::reborrow::Reborrow;
use faer::{MatMut, MatRef};
use vdd_core::{CoreError, Policy, Rng, Seeds, check_act_args, check_finite, check_shape};

use crate::TaskError;

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
