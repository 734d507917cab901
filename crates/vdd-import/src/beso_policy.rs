//! [`BesoPolicy`]: an imported BESO/D3IL teacher acting as `BesoAgent.predict` does.

use std::collections::VecDeque;

use faer::Mat;
use vdd_core::{CoreError, Policy, Seeds, check_act_args};

use crate::beso::BesoTeacher;
use crate::beso_error::BesoError;
use crate::karras::{KarrasBuffers, sample};

/// A [`BesoTeacher`] as a [`Policy`], following `BesoAgent.predict` of D3IL and BESO:
///
/// 1. scale the observation and append it to the observation window (at most `window`);
/// 2. draw `σ_max · z` for the new action and put the window's previous (clean, scaled)
///    actions before it, so the network sees as many actions as observations;
/// 3. run the agent's sampler on that whole action window over its σ schedule;
/// 4. keep the last action, clamp it to the scaler's action box, remember it for the next
///    step's window, and return it unscaled.
///
/// An observation row is one observation followed by the goals (`goal_window` observations'
/// width) for goal-conditioned teachers.
#[derive(Debug, Clone)]
pub struct BesoPolicy {
    teacher: BesoTeacher,
    obs_context: VecDeque<Vec<f32>>,
    action_context: VecDeque<Vec<f32>>,
    rng: vdd_core::Rng,
    sigmas: Vec<f32>,
    buf: KarrasBuffers,
}

impl BesoPolicy {
    /// The policy of `teacher`, with its noise stream seeded by `seed`.
    pub fn new(teacher: BesoTeacher, seed: u64) -> Result<Self, BesoError> {
        let c = teacher.config();
        let sigmas = c.schedule.sigmas(c.steps, c.sigma_min, c.sigma_max)?;
        Ok(Self {
            teacher,
            obs_context: VecDeque::new(),
            action_context: VecDeque::new(),
            rng: Seeds::new(seed).stream("beso-policy"),
            sigmas,
            buf: KarrasBuffers::default(),
        })
    }

    /// The teacher.
    pub fn teacher(&self) -> &BesoTeacher {
        &self.teacher
    }

    /// One step with the noise given by `noise` (`BesoAgent.predict` with its
    /// `torch.randn` calls replaced): `noise` is called first for the new action's initial
    /// draw (`action_dim` floats), then as [`crate::karras::sample`] describes.
    pub fn act_with_noise(
        &mut self,
        obs: &[f32],
        action: &mut [f32],
        noise: &mut dyn FnMut(&mut [f32]),
    ) -> Result<(), BesoError> {
        check_act_args(self, obs, action)?;
        let c = self.teacher.config().clone();
        let (od, ad) = (c.obs_dim(), c.action_dim());
        let mut o = obs[..od].to_vec();
        c.scaler.obs.normalize(&mut o);
        let mut goal = obs[od..].to_vec();
        c.scaler.obs.normalize(&mut goal);
        if self.obs_context.len() == c.window {
            self.obs_context.pop_front();
        }
        self.obs_context.push_back(o);
        let t = self.obs_context.len();
        let mut states = Mat::<f32>::zeros(1, t * od + goal.len());
        for (k, ob) in self.obs_context.iter().enumerate() {
            for (j, v) in ob.iter().enumerate() {
                states[(0, k * od + j)] = *v;
            }
        }
        for (j, v) in goal.iter().enumerate() {
            states[(0, t * od + j)] = *v;
        }
        let mut fresh = vec![0.0f32; ad];
        noise(&mut fresh);
        let mut x = Mat::<f32>::zeros(1, t * ad);
        for (k, a) in self.action_context.iter().enumerate() {
            for (j, v) in a.iter().enumerate() {
                x[(0, k * ad + j)] = *v;
            }
        }
        let last = (t - 1) * ad;
        for (j, z) in fresh.iter().enumerate() {
            x[(0, last + j)] = z * c.sigma_max;
        }
        let teacher = &mut self.teacher;
        let mut den = |a: faer::MatRef<'_, f32>, s: &[f32], out: faer::MatMut<'_, f32>| {
            teacher.denoise(states.as_ref(), a, s, out)
        };
        sample(&mut den, c.sampler, &self.sigmas, x.as_mut(), noise, &mut self.buf)?;
        let mut a: Vec<f32> = (0..ad).map(|j| x[(0, last + j)]).collect();
        for (j, v) in a.iter_mut().enumerate() {
            *v = v.clamp(c.scaler.action_min[j], c.scaler.action_max[j]);
        }
        if c.window > 1 {
            if self.action_context.len() == c.window - 1 {
                self.action_context.pop_front();
            }
            self.action_context.push_back(a.clone());
        }
        c.scaler.action.denormalize(&mut a);
        action.copy_from_slice(&a);
        Ok(())
    }
}

impl Policy for BesoPolicy {
    fn obs_dim(&self) -> usize {
        let c = self.teacher.config();
        (1 + c.goal_window) * c.obs_dim()
    }

    fn action_dim(&self) -> usize {
        self.teacher.config().action_dim()
    }

    fn reset(&mut self) {
        self.obs_context.clear();
        self.action_context.clear();
    }

    fn seed(&mut self, seed: u64) {
        self.rng = Seeds::new(seed).stream("beso-policy");
    }

    fn act_into(&mut self, obs: &[f32], action: &mut [f32]) -> Result<(), CoreError> {
        let mut rng = self.rng.clone();
        let r =
            self.act_with_noise(obs, action, &mut |b| vdd_core::fill_standard_normal(&mut rng, b));
        self.rng = rng;
        Ok(r?)
    }
}
