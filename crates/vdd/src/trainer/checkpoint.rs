//! Checkpoints of a VDD run: the trainer's files in one directory ([`Vdd::write_checkpoint`]),
//! committed as a crash-safe generation of a [`CheckpointDir`] ([`Vdd::save_checkpoint`]), and
//! resuming with every part of the state checked against the student and the settings'
//! ranges ([`Vdd::resume`]).
//!
//! A generation holds `student.safetensors` (the student) and `trainer.json` (the settings,
//! the iteration, both optimisers and the moving average). The random draws of iteration `i`
//! come from streams indexed by `i` of the run's seed, so the iteration is the whole random
//! state: a resumed run continues bit for bit.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use vdd_core::{Expert, ScoreModel};
use vdd_moe::{ExpertFamily, Moe};
use vdd_nn::checkpoint::{self, CheckpointDir};
use vdd_nn::{Adam, Ema};

use super::{DistillData, Vdd};
use crate::config::VddConfig;
use crate::error::VddError;

#[derive(Serialize, Deserialize)]
struct TrainerState {
    config: VddConfig,
    iteration: usize,
    expert_optimizer: Adam,
    gating_optimizer: Adam,
    #[serde(default)]
    student_ema: Option<Ema>,
    /// The convergence probe's measurements so far (absent in older checkpoints).
    #[serde(default)]
    probes: Vec<(usize, f32)>,
}

const STUDENT: &str = "student.safetensors";
const STATE: &str = "trainer.json";

/// Largest `trainer.json` read: two Adam moments and a moving average of a model of
/// [`MAX_PARAMS`](vdd_nn::limits::MAX_PARAMS) values, at most 32 bytes of JSON each, and 1 MiB
/// for the rest.
pub const MAX_STATE_BYTES: u64 = 3 * vdd_nn::limits::MAX_PARAMS as u64 * 32 + (1 << 20);

impl<S: ScoreModel, E: Expert> Vdd<S, E> {
    /// Writes the trainer's files into the existing directory `dir` (`student.safetensors`,
    /// `trainer.json`), overwriting them. Crash safety comes from [`Vdd::save_checkpoint`],
    /// which calls this on a fresh generation directory.
    ///
    /// What is written can be resumed: the state is first checked with [`Vdd::resume`]'s rules
    /// (the student's weights and normalisers by [`Moe::save`], the optimisers' moments by
    /// [`Adam::check`], the moving average by [`Ema::validate`]), and a value breaking them is
    /// an error ([`VddError::CheckpointInvalid`]) naming it, before anything is written.
    pub fn write_checkpoint(&self, dir: &Path) -> Result<(), VddError> {
        let invalid = |what: &'static str| {
            move |e: vdd_nn::NnError| VddError::CheckpointInvalid {
                path: dir.to_owned(),
                what,
                source: e.into(),
            }
        };
        self.expert_optimizer
            .check(self.student.expert_networks())
            .map_err(invalid("expert optimiser"))?;
        match self.student.gating_network() {
            Some(net) => self.gating_optimizer.check(net),
            None if self.gating_optimizer.steps() == 0 => Ok(()),
            None => Err(vdd_nn::NnError::ModelMismatch(
                "steps on a student without a learned gating".into(),
            )),
        }
        .map_err(invalid("gating optimiser"))?;
        if let Some(ema) = &self.student_ema {
            ema.validate(&self.student).map_err(invalid("student average"))?;
        }
        self.student.save(&dir.join(STUDENT))?;
        let state = TrainerState {
            config: self.config.clone(),
            iteration: self.iteration,
            expert_optimizer: self.expert_optimizer.clone(),
            gating_optimizer: self.gating_optimizer.clone(),
            student_ema: self.student_ema.clone(),
            probes: self.probes.clone(),
        };
        let path = dir.join(STATE);
        let json = serde_json::to_vec(&state)
            .map_err(|source| VddError::CheckpointFormat { path: path.clone(), source })?;
        vdd_nn::io::write_atomic(&path, &json)?;
        Ok(())
    }

    /// Commits the state after [`Vdd::iteration`] iterations as generation `iteration` of
    /// `store` (see [`vdd_nn::checkpoint`]: a crash at any point leaves the previous
    /// generation, or this one, complete), and returns its directory.
    ///
    /// ```
    /// use vdd::{faer::Mat, DistillData, MoeConfig, Vdd, VddConfig};
    /// use vdd_core::gmm::{Gmm, GmmTeacher};
    /// use vdd_nn::checkpoint::CheckpointDir;
    /// let root = std::env::temp_dir().join(format!("vdd-save-doc-{}", std::process::id()));
    /// let data = DistillData::from_states(Mat::zeros(4, 1))?;
    /// let config = VddConfig { iterations: 4, batch_size: 4, vi_samples: 4, ..VddConfig::toy() };
    /// let teacher = GmmTeacher::fixed(Gmm::circle(2, 1.0, 0.5, 0.0)?, 1);
    /// let mut vdd = Vdd::from_config(config, teacher.clone(), MoeConfig::toy(1, 2, 2), data.clone())?;
    /// let store = CheckpointDir::open(&root)?;
    /// vdd.step()?;
    /// vdd.save_checkpoint(&store)?;
    /// drop(store);
    /// let resumed = Vdd::resume(&root, teacher, data)?; // the newest complete generation
    /// assert_eq!(resumed.iteration(), 1);
    /// # std::fs::remove_dir_all(&root)?;
    /// # Ok::<(), Box<dyn std::error::Error>>(())
    /// ```
    pub fn save_checkpoint(&self, store: &CheckpointDir) -> Result<PathBuf, VddError> {
        store.commit(self.iteration as u64, |dir| self.write_checkpoint(dir))
    }

    /// Resumes a run from a checkpoint with a custom expert family: `dir` is a
    /// [`CheckpointDir`] (its newest complete generation is read) or a directory written by
    /// [`Vdd::write_checkpoint`]. Continuing gives exactly the numbers of an uninterrupted run.
    ///
    /// Everything is checked before it is used: the settings' ranges ([`VddConfig::validate`]),
    /// the iteration, the optimisers' hyper-parameters against the settings and their moments
    /// against the student's networks ([`Adam::check`]), and the moving average against the
    /// student ([`Ema::validate`]); errors name the part and the tensor.
    pub fn resume_with_family(
        dir: &Path,
        teacher: S,
        expert: E,
        data: DistillData,
    ) -> Result<Self, VddError> {
        let dir = generation(dir)?;
        let student = Moe::load_with_family(&dir.join(STUDENT), expert)?;
        Self::resume_inner(&dir, teacher, student, data)
    }

    fn resume_inner(
        dir: &Path,
        teacher: S,
        student: Moe<E>,
        data: DistillData,
    ) -> Result<Self, VddError> {
        let path = dir.join(STATE);
        let bytes = vdd_core::files::read_bounded(&path, MAX_STATE_BYTES)
            .map_err(|source| VddError::CheckpointIo { path: path.clone(), source })?;
        let state: TrainerState = serde_json::from_slice(&bytes)
            .map_err(|source| VddError::CheckpointFormat { path, source })?;
        let invalid = |what: &'static str| {
            move |e: Box<dyn std::error::Error + Send + Sync>| VddError::CheckpointInvalid {
                path: dir.to_owned(),
                what,
                source: e,
            }
        };
        state.config.validate().map_err(|e| invalid("settings")(e.into()))?;
        if state.iteration > state.config.iterations {
            let (i, n) = (state.iteration, state.config.iterations);
            return Err(invalid("iteration")(format!("{i} is beyond the run's {n}").into()));
        }
        let mut vdd = Self::new(state.config, teacher, student, data)?;
        vdd.iteration = state.iteration;
        for (what, opt, settings) in [
            ("expert optimiser", &state.expert_optimizer, &vdd.config.expert_optimizer),
            ("gating optimiser", &state.gating_optimizer, &vdd.config.gating_optimizer),
        ] {
            if opt.config() != settings {
                let e = format!(
                    "hyper-parameters {:?} differ from the settings' {settings:?}",
                    opt.config()
                );
                return Err(invalid(what)(e.into()));
            }
        }
        let nets = vdd.student.expert_networks_mut();
        state.expert_optimizer.check(nets).map_err(|e| invalid("expert optimiser")(e.into()))?;
        match vdd.student.gating_network_mut() {
            Some(net) => state.gating_optimizer.check(net),
            None if state.gating_optimizer.steps() == 0 => Ok(()),
            None => Err(vdd_nn::NnError::ModelMismatch(
                "steps on a student without a learned gating".into(),
            )),
        }
        .map_err(|e| invalid("gating optimiser")(e.into()))?;
        vdd.expert_optimizer = state.expert_optimizer;
        vdd.gating_optimizer = state.gating_optimizer;
        if let Some(p) = state.probes.iter().find(|p| p.0 > state.iteration || !p.1.is_finite()) {
            let e = format!("a measurement after {} iterations: {}", p.0, p.1);
            return Err(invalid("convergence probe")(e.into()));
        }
        vdd.probes = state.probes;
        match (state.student_ema, vdd.config.student_ema) {
            (Some(ema), Some(decay)) => {
                ema.validate(&vdd.student).map_err(|e| invalid("student average")(e.into()))?;
                if ema.decay() != decay {
                    let e = format!("decay {} differs from the settings' {decay}", ema.decay());
                    return Err(invalid("student average")(e.into()));
                }
                vdd.student_ema = Some(ema);
            }
            (Some(_), None) => {
                let e = "present, but the settings have no student_ema".into();
                return Err(invalid("student average")(e));
            }
            // A checkpoint written without an average starts one at the resumed student.
            (None, _) => {}
        }
        Ok(vdd)
    }
}

impl<S: ScoreModel> Vdd<S, ExpertFamily> {
    /// Resumes a run from a checkpoint (built-in expert families); see
    /// [`Vdd::resume_with_family`].
    pub fn resume(dir: &Path, teacher: S, data: DistillData) -> Result<Self, VddError> {
        let dir = generation(dir)?;
        let student = Moe::load(&dir.join(STUDENT))?;
        Self::resume_inner(&dir, teacher, student, data)
    }
}

/// The newest complete generation of a checkpoint directory, or `dir` itself when it is not one
/// (no `LATEST` pointer).
fn generation(dir: &Path) -> Result<PathBuf, VddError> {
    match checkpoint::latest(dir)? {
        Some((_, generation)) => Ok(generation),
        None if dir.join(STATE).is_file() => Ok(dir.to_owned()),
        None => Err(VddError::CheckpointIo {
            path: dir.to_owned(),
            source: std::io::Error::new(std::io::ErrorKind::NotFound, "no complete checkpoint"),
        }),
    }
}
