//! A VDD training that survives being killed ([`Resumable::run`]): it commits the trainer to a
//! [`CheckpointDir`] every few seconds of training, continues from the newest complete
//! generation when asked (bit for bit, see [`Vdd::resume`]), records curves over training
//! through a [`CurveProbe`], and removes its checkpoints when done.

use std::io::ErrorKind;
use std::path::Path;
use std::time::Instant;

use vdd_core::curves::{CurveEval, CurveProbe, Curves};
use vdd_core::{ScoreModel, Snapshot};
use vdd_moe::Moe;
use vdd_nn::checkpoint::CheckpointDir;

use super::{DistillData, IterationMetrics, Vdd};
use crate::config::VddConfig;
use crate::error::VddError;

/// Where and how often a [`Resumable::run`] checkpoints.
#[derive(Debug, Clone, Copy)]
pub struct Resumable<'a> {
    /// The run's checkpoint directory (a [`CheckpointDir`] root), removed when the run ends.
    pub dir: &'a Path,
    /// Continue from the newest complete generation in `dir`; `false` discards what is there.
    pub resume: bool,
    /// Seconds of training between commits (commits and curves are not training time).
    pub every_seconds: u64,
    /// Checkpoint selection: keep the snapshot with the highest value of this series of the
    /// probe's curves (e.g. held-out task entropy, as the paper's official code selects), in
    /// [`ResumableOutcome::selected`]. `None`: keep nothing (the final iterate only).
    pub select_by: Option<&'a str>,
}

/// The snapshot a [`Resumable::select_by`] run kept: the best of the probe's checkpoints.
#[derive(Debug, Clone)]
pub struct Selected {
    /// The iterations done when it was taken.
    pub iteration: usize,
    /// Its value in the selection series.
    pub value: f64,
    /// The student then.
    pub student: Moe,
}

/// What a [`Resumable::run`] returns.
#[derive(Debug, Clone)]
pub struct ResumableOutcome {
    /// The trained student ([`Vdd::into_student`]).
    pub student: Moe,
    /// Wall-clock seconds of training over every session of the run, without commits and
    /// curve evaluations.
    pub train_seconds: f64,
    /// The training curves (expert and gating entropies, corrected-score rms, log
    /// responsibility, gating loss; 200 points a series) and the probe's curves over training.
    pub curves: Curves,
    /// The mean noise level the teacher was queried at.
    pub mean_noise_level: f32,
    /// The snapshot kept by [`Resumable::select_by`] (`None` without it, or when the probe
    /// took no checkpoint).
    pub selected: Option<Selected>,
}

/// The file beside the trainer's in a generation: the curves, the noise levels' sum, the
/// training and the curve seconds so far.
const PROGRESS: &str = "progress.json";

/// Largest `progress.json` read (the curves of a run; a real one has a few MB).
const MAX_PROGRESS_BYTES: u64 = 1 << 30;

/// The selected snapshot in a generation ([`Resumable::select_by`]): its iteration and value
/// (`selected.json`) and the student (`selected.safetensors`).
const SELECTED: (&str, &str) = ("selected.json", "selected.safetensors");

/// Largest `selected.json` read.
const MAX_SELECTED_BYTES: u64 = 1 << 16;

/// Writes `best` into the generation `dir`.
fn write_selected(dir: &Path, best: &Selected) -> Result<(), VddError> {
    best.student.save(&dir.join(SELECTED.1))?;
    let path = dir.join(SELECTED.0);
    let json = serde_json::to_vec(&(best.iteration, best.value))
        .map_err(|source| VddError::CheckpointFormat { path: path.clone(), source })?;
    Ok(vdd_nn::io::write_atomic(&path, &json)?)
}

/// The selected snapshot of the generation `dir`, if it has one.
fn read_selected(dir: &Path) -> Result<Option<Selected>, VddError> {
    let path = dir.join(SELECTED.0);
    if !path.is_file() {
        return Ok(None);
    }
    let bytes = vdd_core::files::read_bounded(&path, MAX_SELECTED_BYTES)
        .map_err(|source| VddError::CheckpointIo { path: path.clone(), source })?;
    let (iteration, value): (usize, f64) = serde_json::from_slice(&bytes)
        .map_err(|source| VddError::CheckpointFormat { path: path.clone(), source })?;
    if !value.is_finite() {
        let source = format!("selection value {value} is not finite").into();
        return Err(VddError::CheckpointInvalid { path, what: "selected snapshot", source });
    }
    let student = Moe::load(&dir.join(SELECTED.1))?;
    Ok(Some(Selected { iteration, value, student }))
}

impl Resumable<'_> {
    /// Distils `teacher` into `student` (freshly initialised) on `data` with `config`, or
    /// resumes from `self.dir` under `self.resume` (refusing a checkpoint of other settings or
    /// another student), calling `report` after every iteration. At each checkpoint of
    /// `probe`, the [`Snapshot`](vdd_core::Snapshot) of the student, made a policy by
    /// `policy`, is evaluated; the probe's [`CurveProbe::seconds`] is its time, over every
    /// session of the run.
    ///
    /// ```
    /// use vdd::faer::Mat;
    /// use vdd::gmm::{Gmm, GmmTeacher};
    /// use vdd::trainer::Resumable;
    /// use vdd::{DistillData, Moe, MoeConfig, VddConfig, VddError};
    /// use vdd_core::curves::{CurveEval, CurveProbe};
    ///
    /// let dir = std::env::temp_dir().join(format!("vdd-resumable-doc-{}", std::process::id()));
    /// let config = VddConfig { iterations: 20, batch_size: 4, vi_samples: 4, ..VddConfig::toy() };
    /// let teacher = GmmTeacher::fixed(Gmm::circle(2, 1.0, 0.5, 0.0)?, 1);
    /// let student = Moe::from_config(MoeConfig::toy(1, 2, 2), config.seed)?;
    /// let data = DistillData::from_states(Mat::zeros(4, 1))?;
    /// let run = Resumable { dir: &dir, resume: false, every_seconds: 10, select_by: None };
    /// // No curves over training: a probe without an evaluation.
    /// let mut probe = CurveProbe::<Moe, dyn CurveEval<Moe, Error = VddError>>::new(None, 0);
    /// let out = run.run((config, teacher, student, data), &mut probe, Ok::<_, VddError>, |_| {})?;
    /// assert!(out.curves.contains_key("gating entropy (nats)") && !dir.exists());
    /// # Ok::<(), Box<dyn std::error::Error>>(())
    /// ```
    pub fn run<S: ScoreModel, P, C, E>(
        &self,
        (config, teacher, student, data): (VddConfig, S, Moe, DistillData),
        probe: &mut CurveProbe<'_, P, C>,
        policy: impl Fn(Moe) -> Result<P, E>,
        mut report: impl FnMut(&IterationMetrics),
    ) -> Result<ResumableOutcome, E>
    where
        C: ?Sized + CurveEval<P>,
        E: From<VddError> + From<C::Error>,
    {
        let root = self.dir;
        let io = |source| VddError::CheckpointIo { path: root.to_owned(), source };
        // The lock first: a live writer's checkpoints are never removed (an error instead).
        let store = CheckpointDir::open(root).map_err(VddError::from)?;
        if !self.resume {
            store.clear().map_err(VddError::from)?;
        }
        let iterations = config.iterations;
        let latest = store.latest().map_err(VddError::from)?;
        let mut best: Option<Selected> = None;
        let (mut curves, mut noise_sum, mut train_seconds, mut vdd) = match latest {
            Some((_, generation)) => {
                let path = generation.join(PROGRESS);
                let bytes = vdd_core::files::read_bounded(&path, MAX_PROGRESS_BYTES)
                    .map_err(|source| VddError::CheckpointIo { path: path.clone(), source })?;
                let (c, n, t, curve_seconds): (Curves, f64, f64, f64) =
                    serde_json::from_slice(&bytes)
                        .map_err(|source| VddError::CheckpointFormat { path, source })?;
                probe.seconds += curve_seconds; // the earlier sessions' curves
                let vdd = Vdd::resume(&generation, teacher, data)?;
                if self.select_by.is_some() {
                    best = read_selected(&generation)?;
                }
                if vdd.config() != &config || vdd.student().config() != student.config() {
                    let source = "written with other settings or another student".into();
                    let what = "settings";
                    return Err(E::from(VddError::CheckpointInvalid {
                        path: generation,
                        what,
                        source,
                    }));
                }
                (c, n, t, vdd)
            }
            None => (Curves::default(), 0.0, 0.0, Vdd::new(config, teacher, student, data)?),
        };
        let every = (iterations / 200).max(1);
        let at = probe.checkpoints(iterations);
        let mut t0 = Instant::now();
        while vdd.iteration() < iterations {
            let m = vdd.step()?;
            if at.contains(&vdd.iteration()) {
                train_seconds += t0.elapsed().as_secs_f64();
                let snapshot = vdd.snapshot()?;
                let kept = self.select_by.map(|series| (series, snapshot.clone()));
                probe.record(vdd.iteration(), &policy(snapshot)?)?;
                if let Some((series, student)) = kept {
                    let value = selection_value(probe, series)?;
                    if best.as_ref().is_none_or(|b| value > b.value) {
                        best = Some(Selected { iteration: vdd.iteration(), value, student });
                    }
                }
                probe.take_into(&mut curves);
                t0 = Instant::now(); // the curves are not training time
            }
            report(&m);
            noise_sum += f64::from(m.expert.noise_level);
            if m.iteration % every == 0 || m.iteration + 1 == iterations {
                let x = m.iteration as f64;
                let mut push =
                    |k: &str, v: f64| curves.entry(k.to_owned()).or_default().push((x, v));
                push("expert entropy (nats)", f64::from(m.expert.expert_entropy));
                push("corrected score rms", f64::from(m.expert.corrected_score_rms));
                push("log responsibility", f64::from(m.expert.log_responsibility));
                push("gating entropy (nats)", f64::from(m.gating_entropy));
                if let Some(g) = m.gating_loss {
                    push("gating loss", f64::from(g));
                }
            }
            if t0.elapsed().as_secs() >= self.every_seconds && vdd.iteration() < iterations {
                train_seconds += t0.elapsed().as_secs_f64();
                let progress = (&curves, noise_sum, train_seconds, probe.seconds);
                store.commit(vdd.iteration() as u64, |dir| -> Result<(), VddError> {
                    vdd.write_checkpoint(dir)?;
                    if let Some(best) = &best {
                        write_selected(dir, best)?;
                    }
                    let path = dir.join(PROGRESS);
                    let json = serde_json::to_vec(&progress).map_err(|source| {
                        VddError::CheckpointFormat { path: path.clone(), source }
                    })?;
                    Ok(vdd_nn::io::write_atomic(&path, &json)?)
                })?;
                t0 = Instant::now(); // the training time leaves the commits out
            }
        }
        train_seconds += t0.elapsed().as_secs_f64();
        store.clear().map_err(VddError::from)?;
        drop(store); // removes `LOCK` while holding it
        // The directory itself when empty; another writer may have opened it meanwhile.
        match std::fs::remove_dir(root) {
            Err(e) if !matches!(e.kind(), ErrorKind::NotFound | ErrorKind::DirectoryNotEmpty) => {
                return Err(E::from(io(e)));
            }
            _ => {}
        }
        let mean_noise_level = (noise_sum / iterations.max(1) as f64) as f32;
        let student = vdd.into_student();
        Ok(ResumableOutcome { student, train_seconds, curves, mean_noise_level, selected: best })
    }
}

/// The value `probe` just recorded in `series`, or an error naming the series it has.
fn selection_value<P, C: ?Sized + CurveEval<P>>(
    probe: &CurveProbe<'_, P, C>,
    series: &str,
) -> Result<f64, VddError> {
    let value = probe.curves.get(series).and_then(|points| points.last()).map(|p| p.1);
    match value {
        Some(v) if v.is_finite() => Ok(v),
        Some(v) => Err(vdd_core::CoreError::Config(format!(
            "checkpoint selection: `{series}` is {v} at a checkpoint"
        ))
        .into()),
        None => {
            let names: Vec<&str> = probe.curves.keys().map(String::as_str).collect();
            Err(vdd_core::CoreError::Config(format!(
                "checkpoint selection: the curves over training have no series `{series}` \
                 (they have: {})",
                if names.is_empty() { "none".to_owned() } else { names.join(", ") }
            ))
            .into())
        }
    }
}
