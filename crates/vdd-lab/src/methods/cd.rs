//! `cd`: consistency distillation of the BESO teacher. Keys: `baselines.cd` (the [`CdConfig`];
//! its seed is replaced by the run seed) and `baselines.consistency_follows_teacher` (a student
//! started from the teacher, `init_from_teacher`, takes the teacher's network architecture and
//! levels `σ_data`, `σ_min`, `σ_max`, `ρ`, so `--set teachers.beso...` needs no matching change).

use std::time::Instant;

use vdd_consistency::{CdConfig, CdTrainer, ConsistencyProgress, ConsistencyStep, LossMeter};
use vdd_core::Snapshot;
use vdd_diffusion::{Beso, BesoConfig, DiffusionTeacher};

use crate::method::{
    Budget, Capability, CurveProbe, Info, Job, Method, MethodRecipe, Row, TeacherUse, Trained,
};
use crate::plots::Curves;
use crate::policy::TrainedPolicy;

/// CD.
pub struct Cd;

const INFO: Info = Info {
    name: "cd",
    teacher: TeacherUse::Learned,
    needs: &[Capability::Rollouts],
    row_keys: &[],
};

/// The key of `consistency_follows_teacher` (CD and CTM).
pub const FOLLOW: &str = "baselines.consistency_follows_teacher";

impl Method for Cd {
    fn info(&self) -> &Info {
        &INFO
    }
    fn keys(&self, _: &Row) -> Vec<String> {
        vec!["baselines.cd".into(), FOLLOW.into()]
    }
    fn check(&self, recipe: &MethodRecipe<'_>) -> crate::Result {
        recipe.get::<CdConfig>("baselines.cd")?;
        recipe.get::<bool>(FOLLOW).map(drop)
    }
    fn train(&self, job: &Job<'_>) -> crate::Result<Trained> {
        let train = job.recipe.get::<CdConfig>("baselines.cd")?.train;
        let budget = Budget::student(train.steps, train.batch_size);
        let trained = distil(job, |beso, follow, curves, probe| {
            let c = job.recipe.get("baselines.cd")?;
            let c = config_for(&c, beso.config(), job.seed, follow);
            let (steps, every) = (c.sampling_steps, c.train.log_every);
            let (states, actions) = (job.data.states.as_ref(), job.data.actions.as_ref());
            let mut trainer = CdTrainer::new(c, beso, states, actions)?;
            let model = run_trainer(&mut trainer, every, job, (curves, probe), |m| {
                Ok(TrainedPolicy::Consistency(Box::new(m)))
            })?;
            Ok((TrainedPolicy::Consistency(Box::new(model)), steps))
        })?;
        Ok(Trained { budget: Some(budget), ..trained })
    }
}

/// Runs `train` (given the BESO teacher, `consistency_follows_teacher`, the curves to fill and
/// the probe of the curves over training; returning the policy and its sampling steps) and
/// times it: CD and CTM.
pub fn distil(
    job: &Job<'_>,
    train: impl FnOnce(
        Beso,
        bool,
        &mut Curves,
        &mut CurveProbe<'_>,
    ) -> crate::Result<(TrainedPolicy, usize)>,
) -> crate::Result<Trained> {
    let t = job.teacher()?;
    let DiffusionTeacher::Beso(beso) = t.teacher.clone() else {
        return Err("CD and CTM need the BESO teacher".into());
    };
    let follow = job.recipe.get(FOLLOW)?;
    let mut curves = Curves::default();
    let t0 = Instant::now();
    let mut probe = job.probe();
    let (policy, steps) = train(beso, follow, &mut curves, &mut probe)?;
    let curve_seconds = probe.take_into(&mut curves);
    Ok(Trained {
        teacher_seconds: Some(t.train_seconds),
        sampling_steps: Some(steps),
        curve_seconds,
        ..Trained::new(policy, t0.elapsed().as_secs_f64() - curve_seconds, curves)
    })
}

/// Trains a CD / CTM `trainer` to its end with a progress bar, the loss curves (means over
/// `log_every` steps) and the curves over training (`policy` makes a snapshot a policy);
/// returns the distilled model.
pub fn run_trainer<T: Snapshot<Report = ConsistencyStep>>(
    trainer: &mut T,
    log_every: u64,
    job: &Job<'_>,
    (curves, probe): (&mut Curves, &mut CurveProbe<'_>),
    policy: impl Fn(T::Output) -> crate::Result<TrainedPolicy>,
) -> crate::Result<T::Output>
where
    crate::LabError: From<T::Error>,
{
    let total = trainer.iterations() as u64;
    let every = log_every.max(1);
    let bar = crate::progress::bar(total, job.label);
    let (mut meter, t0) = (LossMeter::default(), Instant::now());
    let report = |s: &ConsistencyStep| {
        meter.add(s);
        let done = s.step + 1;
        if done % every == 0 || done == total {
            record(
                curves,
                bar.as_ref(),
                &meter.report(done, total, s.lr, t0.elapsed().as_secs_f64()),
            );
        }
    };
    probe.run(trainer, report, policy)?;
    bar.finish_and_clear();
    Ok(trainer.snapshot()?)
}

/// A CD / CTM configuration for `seed`, with (`follow_teacher`) the teacher's architecture and
/// levels ([`CdConfig::following_teacher`]). (Their learning rate decays over their
/// `train.steps` by construction.)
pub fn config_for(c: &CdConfig, beso: &BesoConfig, seed: u64, follow_teacher: bool) -> CdConfig {
    let c = c.clone().with_seed(seed);
    if follow_teacher { c.following_teacher(beso) } else { c }
}

/// Records a training report in the progress bar and the curves.
pub fn record(curves: &mut Curves, bar: &dyn crate::progress::Bar, p: &ConsistencyProgress) {
    bar.set_position(p.step);
    bar.set_message(format!("loss {:.4}", p.loss));
    let x = p.step as f64;
    curves.entry("consistency loss".into()).or_default().push((x, f64::from(p.consistency_loss)));
    if p.dsm_loss != 0.0 {
        curves.entry("DSM loss".into()).or_default().push((x, f64::from(p.dsm_loss)));
    }
}
