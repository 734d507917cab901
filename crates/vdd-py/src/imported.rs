//! `vdd.distill` with a teacher imported from PyTorch (`vdd.import_lerobot`): the wiring of
//! the Rust experiment path (`vdd-lab`'s imported teacher source and its VDD rows) without the
//! experiment layer, which this binding may not depend on (docs/architecture.md).
//!
//! The teacher works in its own normalised chunk space ([`vdd::TeacherSpace`] from
//! [`UnetTeacher::teacher_space`]); its denoised chunk is clamped to the box of the training
//! chunks (`actions`) widened by a margin, as the recipe's `vdd.clamp_denoiser`; the
//! student starts from a mixture fitted to the teacher's own samples ([`AutoPlan`], as
//! `Vdd::in_teacher_space` with `init_from_teacher`; the recipe's default start, EM on the
//! teacher's samples, is `vdd_lab::sample_fit`, which needs `vdd-mixture`); VDD then runs with
//! noise on both sides over the lower 30 % of the teacher's trained steps, as the recipe's
//! `[vdd.imported]`; the student emits the teacher's whole chunk and acts as the teacher's
//! package does ([`UnetTeacher::chunk_deploy_spec`]).

use faer::Mat;
use vdd::{AutoOptions, AutoPlan, DistillData, Moe, ScoreAt, TeacherSpace, Vdd};
use vdd_core::{ClampedDenoiser, CoreError, NoiseSchedule};
use vdd_import::UnetTeacher;

use crate::settings::{Extra, Request, RunError, apply_settings};

/// The clamp's margin around the training chunks' box (the teacher's normalised units), as the
/// recipe's `vdd.clip_margin`.
pub const CLIP_MARGIN: f32 = 0.5;
/// Teacher samples the plan fits the student's start to (as `Vdd::in_teacher_space`).
pub const TEACHER_SAMPLES: usize = 2048;
/// Highest noise level drawn, as a share of the teacher's trained steps `N` (the recipe's 30 of
/// 100: σ ≈ 0.5 of the normalised chunk for `squaredcos_cap_v2`).
pub const TOP_LEVEL_SHARE: f32 = 0.3;

fn core(e: impl Into<CoreError>) -> RunError {
    RunError::Vdd(e.into().into())
}

/// Distils `teacher` on raw observation windows `states` and raw chunks `actions` (see the
/// module docs); the student carries the teacher's chunk deployment.
pub(crate) fn train(
    request: &Request,
    extra: &Extra,
    teacher: UnetTeacher,
    states: Mat<f32>,
    actions: Option<Mat<f32>>,
) -> Result<Moe, RunError> {
    let (sn, an) = teacher.teacher_space().map_err(core)?;
    let deploy = teacher.chunk_deploy_spec();
    let n_train = teacher.spec().scheduler.num_train_timesteps as f32;
    let margin = extra.clip_margin.unwrap_or(Some(CLIP_MARGIN));
    let mut clamped = match (margin, &actions) {
        (Some(m), Some(a)) => {
            let a_n = an.normalize_rows(a.as_ref())?;
            ClampedDenoiser::around_data(teacher, a_n.as_ref(), m)?
        }
        (Some(_), None) => {
            return Err(RunError::Setting(
                "an imported teacher's score is clamped around the training chunks: pass them \
                 as actions= (teacher.training_windows gives them), or clip_margin=None to \
                 distil the raw score"
                    .into(),
            ));
        }
        (None, _) => ClampedDenoiser::unclamped(teacher),
    };
    let data =
        DistillData::new(states, actions)?.with_teacher_space(TeacherSpace::normalized(sn, an));
    let options = AutoOptions {
        iterations: request.iterations,
        samples: extra.teacher_samples.unwrap_or(TEACHER_SAMPLES),
        ..AutoOptions::new(request.experts, request.seed)
    };
    let mut plan = AutoPlan::inspect(&mut clamped, &data, &options)?;
    // The recipe's `[vdd.imported]` (recipes/defaults/avoiding.toml), then the user's settings.
    let v = &mut plan.vdd;
    v.score_at = ScoreAt::NoisedSample;
    v.noise =
        NoiseSchedule::Uniform { min: 1.0, max: (TOP_LEVEL_SHARE * n_train).round().max(1.0) };
    v.noise_anneal_until = None;
    (v.batch_size, v.vi_samples, v.chunks, v.gating_batch_size) = (32, 1, 2, 256);
    (v.expert_steps_per_iter, v.gating_steps_per_iter) = (1, 1);
    apply_settings(&mut plan.vdd, &mut plan.student, &request.settings)
        .map_err(RunError::Setting)?;
    let mut vdd = Vdd::from_plan(&plan, clamped, data)?;
    vdd.train(|_| {})?;
    let mut student = vdd.into_student();
    student.set_deploy_spec(deploy)?;
    Ok(student)
}
