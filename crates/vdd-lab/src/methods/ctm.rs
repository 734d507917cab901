//! `ctm`: consistency trajectory model distilled from the BESO teacher. Keys: `baselines.ctm`
//! (the [`CtmConfig`], whose `base` is set up as CD's: [`super::cd::config_for`]) and
//! `baselines.consistency_follows_teacher`.

use vdd_consistency::{CtmConfig, CtmTrainer};

use super::cd;
use crate::method::{
    Budget, Capability, Info, Job, Method, MethodRecipe, Row, TeacherUse, Trained,
};
use crate::policy::TrainedPolicy;

/// CTM.
pub struct Ctm;

const INFO: Info = Info {
    name: "ctm",
    teacher: TeacherUse::Learned,
    needs: &[Capability::Rollouts],
    row_keys: &[],
};

impl Method for Ctm {
    fn info(&self) -> &Info {
        &INFO
    }
    fn keys(&self, _: &Row) -> Vec<String> {
        vec!["baselines.ctm".into(), cd::FOLLOW.into()]
    }
    fn check(&self, recipe: &MethodRecipe<'_>) -> crate::Result {
        recipe.get::<CtmConfig>("baselines.ctm")?;
        recipe.get::<bool>(cd::FOLLOW).map(drop)
    }
    fn train(&self, job: &Job<'_>) -> crate::Result<Trained> {
        let train = job.recipe.get::<CtmConfig>("baselines.ctm")?.base.train;
        let budget = Budget::student(train.steps, train.batch_size);
        let trained = cd::distil(job, |beso, follow, curves, probe| {
            let mut c: CtmConfig = job.recipe.get("baselines.ctm")?;
            c.base = cd::config_for(&c.base, beso.config(), job.seed, follow);
            let (steps, every) = (c.base.sampling_steps, c.base.train.log_every);
            let (states, actions) = (job.data.states.as_ref(), job.data.actions.as_ref());
            let mut trainer = CtmTrainer::new(c, beso, states, actions)?;
            let model = cd::run_trainer(&mut trainer, every, job, (curves, probe), |m| {
                Ok(TrainedPolicy::Trajectory(Box::new(m)))
            })?;
            Ok((TrainedPolicy::Trajectory(Box::new(model)), steps))
        })?;
        Ok(Trained { budget: Some(budget), ..trained })
    }
}
