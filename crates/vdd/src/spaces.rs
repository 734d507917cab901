//! Explicit spaces: the student's, the data's and the teacher's.
//!
//! Three spaces meet in a distillation run:
//!
//! * the **raw** space of the environment, in which [`crate::DistillData`] holds its states
//!   and actions;
//! * the **student's** space, raw values mapped by the student's own normalisers
//!   ([`vdd_moe::Moe::normalizers`]; the identity when it has none), in which its networks
//!   work;
//! * the **teacher's** space, raw values mapped by a [`TeacherSpace`] (the raw space by
//!   default), in which the teacher's [`ScoreModel`] takes actions and states.
//!
//! The trainer does the mapping: it queries the teacher with actions and states in the
//! teacher's space, turns the teacher's score into a score in the student's space (the chain
//! rule of the affine map, `∇_x log p = (s_student / s_teacher) ∇_a log p_T`) and maps teacher
//! samples back. Noise levels stay in the teacher's space and convention. When the two spaces
//! coincide (equal maps, or both absent) nothing is mapped, so such runs compute exactly what
//! they did before spaces were explicit.

use faer::reborrow::ReborrowMut;
use faer::{Mat, MatMut, MatRef};
use rand::RngCore;
use vdd_core::{Affine, CoreError, NoiseConvention, NoiseSchedule, ScoreModel, check_len};

/// How the teacher sees raw states and actions: its inputs are `(raw − offset) / scale` with
/// these maps (`None`: the raw values).
///
/// A learned diffusion teacher of `vdd-diffusion` works in the space of its own normalisers,
/// `TeacherSpace::normalized(teacher.normalizers())`; an analytic teacher written for the
/// environment's units works in the raw space, [`TeacherSpace::raw`] (the default).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TeacherSpace {
    /// The teacher's state map.
    pub states: Option<Affine>,
    /// The teacher's action map.
    pub actions: Option<Affine>,
}

impl TeacherSpace {
    /// The teacher takes raw states and actions.
    pub fn raw() -> Self {
        Self::default()
    }

    /// The teacher takes states and actions normalised by these maps.
    pub fn normalized(states: Affine, actions: Affine) -> Self {
        Self { states: Some(states), actions: Some(actions) }
    }
}

/// `x ← (x − offset) / scale` on every row of `m` (columns = the map's dimensions).
pub(crate) fn normalize_rows(m: &mut Mat<f32>, map: &Affine) {
    for j in 0..m.ncols() {
        let (o, s) = (map.offset[j], map.scale[j]);
        for x in m.col_as_slice_mut(j) {
            *x = (*x - o) / s;
        }
    }
}

/// Whether two optional maps are the same map (absent = the identity).
pub(crate) fn same_map(a: Option<&Affine>, b: Option<&Affine>, dim: usize) -> bool {
    let id = Affine::identity(dim);
    a.unwrap_or(&id) == b.unwrap_or(&id)
}

/// The map from the student's action space to the teacher's, `a = x · scale + offset` per
/// dimension.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct ActionMap {
    scale: Vec<f32>,
    offset: Vec<f32>,
}

impl ActionMap {
    /// The map student → raw → teacher, or `None` when it is the identity.
    pub(crate) fn between(
        student: Option<&Affine>,
        teacher: Option<&Affine>,
        dim: usize,
    ) -> Result<Option<Self>, CoreError> {
        if same_map(student, teacher, dim) {
            return Ok(None);
        }
        let id = Affine::identity(dim);
        let (s, t) = (student.unwrap_or(&id), teacher.unwrap_or(&id));
        check_len("student action normaliser", s.dim(), dim)?;
        check_len("teacher action map", t.dim(), dim)?;
        let scale: Vec<f32> = (0..dim).map(|j| s.scale[j] / t.scale[j]).collect();
        let offset: Vec<f32> = (0..dim).map(|j| (s.offset[j] - t.offset[j]) / t.scale[j]).collect();
        if scale.iter().chain(&offset).any(|v| !v.is_finite()) || scale.iter().any(|v| *v <= 0.0) {
            return Err(CoreError::NonFinite { what: "student-to-teacher action map" });
        }
        Ok(Some(Self { scale, offset }))
    }

    /// `(scale, offset)` of dimension `j`: the teacher's action is `x · scale + offset`.
    pub(crate) fn coefficients(&self, j: usize) -> (f32, f32) {
        (self.scale[j], self.offset[j])
    }
}

/// Calls `f` with the teacher as the student's space sees it: through `map` (a
/// [`MappedTeacher`] using `scratch`) when there is one, else as it is.
pub(crate) fn with_map<R>(
    teacher: &mut dyn ScoreModel,
    map: Option<&ActionMap>,
    scratch: &mut Vec<f32>,
    f: impl FnOnce(&mut dyn ScoreModel) -> R,
) -> R {
    match map {
        None => f(teacher),
        Some(map) => f(&mut MappedTeacher { teacher, map, scratch }),
    }
}

/// The teacher seen from the student's action space through an [`ActionMap`].
pub(crate) struct MappedTeacher<'a, S: ?Sized> {
    pub teacher: &'a mut S,
    pub map: &'a ActionMap,
    pub scratch: &'a mut Vec<f32>,
}

impl<S: ScoreModel + ?Sized> ScoreModel for MappedTeacher<'_, S> {
    fn action_dim(&self) -> usize {
        self.teacher.action_dim()
    }
    fn state_dim(&self) -> usize {
        self.teacher.state_dim()
    }
    fn noise_convention(&self) -> NoiseConvention {
        self.teacher.noise_convention()
    }
    fn score(
        &mut self,
        actions: MatRef<'_, f32>,
        states: MatRef<'_, f32>,
        noise_levels: &[f32],
        mut out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        let (n, d) = (actions.nrows(), actions.ncols());
        check_len("mapped actions (columns)", d, self.map.scale.len())?;
        self.scratch.resize(n * d, 0.0);
        for i in 0..n {
            for j in 0..d {
                self.scratch[i * d + j] = actions[(i, j)] * self.map.scale[j] + self.map.offset[j];
            }
        }
        let teacher_actions = MatRef::from_row_major_slice(self.scratch, n, d);
        self.teacher.score(teacher_actions, states, noise_levels, out.rb_mut())?;
        for j in 0..d {
            let m = self.map.scale[j];
            for i in 0..n {
                out[(i, j)] *= m;
            }
        }
        Ok(())
    }
    fn sample_actions(
        &mut self,
        states: MatRef<'_, f32>,
        rng: &mut dyn RngCore,
        mut out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        self.teacher.sample_actions(states, rng, out.rb_mut())?;
        for j in 0..out.ncols() {
            let (m, c) = (self.map.scale[j], self.map.offset[j]);
            for i in 0..out.nrows() {
                out[(i, j)] = (out[(i, j)] - c) / m;
            }
        }
        Ok(())
    }
    fn draw_noise_levels(
        &self,
        schedule: &NoiseSchedule,
        progress: f32,
        rng: &mut dyn RngCore,
        out: &mut [f32],
    ) {
        self.teacher.draw_noise_levels(schedule, progress, rng, out)
    }
    fn noise_range(&self) -> Option<(f32, f32)> {
        self.teacher.noise_range()
    }
    /// None: the process's denoiser form does not hold in the student's space (below); its
    /// convention, range and levels are forwarded one by one.
    fn noise_process(&self) -> Option<&dyn vdd_core::NoiseProcess> {
        None
    }
    /// None: the map scales the actions, so the teacher's relation between score and denoised
    /// estimate does not hold in the student's space (a clamp works in the teacher's own space).
    fn denoiser_form(&self, _level: f32) -> Option<vdd_core::DenoiserForm> {
        None
    }
    /// None: a view borrowed for one call; the trainer forks the teacher itself.
    fn fork(&self) -> Option<Box<dyn ScoreModel + Send>> {
        None
    }
}

impl<S: ScoreModel> crate::Vdd<vdd_core::ClampedDenoiser<S>> {
    /// VDD for a teacher of its own normalised space (`sn`, `an`; e.g. a diffusion policy
    /// imported from PyTorch, whose actions are chunks) on raw `states` and `actions`: a student
    /// of `mc` (seeded with `vc.seed`) working in that space, and the teacher's denoised
    /// estimate clamped to the normalised `actions`' box widened by `clip_margin` (`None`: the
    /// raw score; a margin must be finite and non-negative). With `init_from_teacher`, the
    /// experts start from a mixture fitted to 2048 of the teacher's samples, with the noise
    /// levels and normalisers [`crate::AutoPlan`] picks (`vc` then gives only the iterations,
    /// the batch and the samples per state).
    pub fn in_teacher_space(
        teacher: S,
        (states, actions): (Mat<f32>, Mat<f32>),
        (sn, an): (Affine, Affine),
        (mc, vc): (&vdd_moe::MoeConfig, &crate::VddConfig),
        (clip_margin, init_from_teacher): (Option<f32>, bool),
    ) -> Result<Self, crate::VddError> {
        let student = vdd_moe::Moe::from_config(mc.clone(), vc.seed)?;
        if !init_from_teacher {
            return Self::continue_in_teacher_space(
                teacher,
                (states, actions),
                (sn, an),
                student,
                vc,
                clip_margin,
            );
        }
        let (mut clamped, data) =
            clamped_in_space(teacher, (states, actions), (sn, an), clip_margin)?;
        let options = crate::AutoOptions {
            iterations: Some(vc.iterations),
            expert_kind: mc.expert_kind,
            gating: mc.gating,
            samples: 2048,
            ..crate::AutoOptions::new(mc.num_experts, vc.seed)
        };
        let mut plan = crate::AutoPlan::inspect(&mut clamped, &data, &options)?;
        (plan.vdd.batch_size, plan.vdd.vi_samples) = (vc.batch_size, vc.vi_samples);
        Self::from_plan(&plan, clamped, data)
    }

    /// As [`Self::in_teacher_space`] without `init_from_teacher`, but VDD continues from
    /// `student` (any mixture of the teacher's dimensions, e.g. one fitted to the teacher's own
    /// samples in its normalised space) instead of a new one: its normalisers are set to the
    /// teacher's (`sn`, `an`), so its networks must work in that normalised space.
    pub fn continue_in_teacher_space(
        teacher: S,
        (states, actions): (Mat<f32>, Mat<f32>),
        (sn, an): (Affine, Affine),
        mut student: vdd_moe::Moe,
        vc: &crate::VddConfig,
        clip_margin: Option<f32>,
    ) -> Result<Self, crate::VddError> {
        student.set_normalizers(Some(sn.clone()), Some(an.clone()))?;
        let (clamped, data) = clamped_in_space(teacher, (states, actions), (sn, an), clip_margin)?;
        Self::new(vc.clone(), clamped, student, data)
    }
}

/// The teacher clamped around the normalised `actions`' box widened by `clip_margin` (`None`:
/// unclamped), and the data in the teacher's normalised space (`sn`, `an`).
fn clamped_in_space<S: ScoreModel>(
    teacher: S,
    (states, actions): (Mat<f32>, Mat<f32>),
    (sn, an): (Affine, Affine),
    clip_margin: Option<f32>,
) -> Result<(vdd_core::ClampedDenoiser<S>, crate::DistillData), crate::VddError> {
    let clamped = match clip_margin {
        Some(m) => vdd_core::ClampedDenoiser::around_data(
            teacher,
            an.normalize_rows(actions.as_ref())?.as_ref(),
            m,
        )?,
        None => vdd_core::ClampedDenoiser::unclamped(teacher),
    };
    let data = crate::DistillData::new(states, Some(actions))?
        .with_teacher_space(TeacherSpace::normalized(sn, an));
    Ok((clamped, data))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn coinciding_spaces_need_no_map_and_others_compose() {
        let a = Affine::new(vec![10.0, -1.0], vec![2.0, 0.5]).unwrap();
        assert_eq!(ActionMap::between(None, None, 2).unwrap(), None);
        assert_eq!(ActionMap::between(Some(&a), Some(&a), 2).unwrap(), None);
        assert_eq!(ActionMap::between(Some(&Affine::identity(2)), None, 2).unwrap(), None);
        // Student x = (raw − 10)/2 → raw = 2x + 10; raw teacher: a = 2x + 10.
        let m = ActionMap::between(Some(&a), None, 2).unwrap().unwrap();
        assert_eq!((m.scale.clone(), m.offset.clone()), (vec![2.0, 0.5], vec![10.0, -1.0]));
        // Teacher normalised by `a`, raw student: a = (x − 10)/2.
        let m = ActionMap::between(None, Some(&a), 2).unwrap().unwrap();
        assert_eq!((m.scale, m.offset), (vec![0.5, 2.0], vec![-5.0, 2.0]));
    }

    /// `N(3, 1)` per dimension in the teacher's space, score `−(a − 3)`.
    struct Three;
    impl ScoreModel for Three {
        fn action_dim(&self) -> usize {
            1
        }
        fn state_dim(&self) -> usize {
            1
        }
        fn score(
            &mut self,
            a: MatRef<'_, f32>,
            _: MatRef<'_, f32>,
            _: &[f32],
            mut out: MatMut<'_, f32>,
        ) -> Result<(), CoreError> {
            for i in 0..a.nrows() {
                out[(i, 0)] = -(a[(i, 0)] - 3.0);
            }
            Ok(())
        }
        fn sample_actions(
            &mut self,
            _: MatRef<'_, f32>,
            _: &mut dyn RngCore,
            mut out: MatMut<'_, f32>,
        ) -> Result<(), CoreError> {
            out.fill(3.0);
            Ok(())
        }
    }

    #[test]
    fn in_teacher_space_clamps_with_a_margin_and_refuses_a_bad_one() {
        let (sn, an) = (Affine::identity(1), Affine::identity(1));
        let data = (faer::mat![[0.0f32], [1.0]], faer::mat![[-1.0f32], [2.0]]);
        let mc = vdd_moe::MoeConfig::toy(1, 1, 2);
        let vc = crate::VddConfig::toy();
        let setup = |clip| {
            let cfg = (&mc, &vc);
            crate::Vdd::in_teacher_space(Three, data.clone(), (sn.clone(), an.clone()), cfg, clip)
        };
        let mut vdd = setup((Some(0.5), false)).unwrap();
        assert_eq!(vdd.teacher_mut().bounds(), Some((&[-1.5f32][..], &[2.5f32][..])));
        assert_eq!(setup((None, false)).unwrap().teacher_mut().bounds(), None);
        for bad in [-0.1, f32::NAN, f32::INFINITY] {
            let e = setup((Some(bad), false)).err().expect("a bad margin is refused");
            assert!(e.to_string().contains("clip margin"), "{e}");
        }
    }

    #[test]
    fn the_mapped_teacher_applies_the_chain_rule_and_maps_samples_back() {
        // Student x = (raw − 1)/2, teacher raw: a = 2x + 1, N(3, 1) is N(1, 0.25) in x.
        let norm = Affine::new(vec![1.0], vec![2.0]).unwrap();
        let map = ActionMap::between(Some(&norm), None, 1).unwrap().unwrap();
        let mut scratch = Vec::new();
        let mut t = MappedTeacher { teacher: &mut Three, map: &map, scratch: &mut scratch };
        let x = faer::mat![[1.0f32], [2.0]];
        let mut out = Mat::zeros(2, 1);
        t.score(x.as_ref(), Mat::zeros(2, 1).as_ref(), &[0.0; 2], out.as_mut()).unwrap();
        assert_eq!((out[(0, 0)], out[(1, 0)]), (0.0, -4.0)); // −(x − 1)/0.25
        let mut rng = vdd_core::Seeds::new(0).stream("s");
        t.sample_actions(Mat::zeros(2, 1).as_ref(), &mut rng, out.as_mut()).unwrap();
        assert_eq!((out[(0, 0)], out[(1, 0)]), (1.0, 1.0));
    }
}
