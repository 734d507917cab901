//! Chunked expert steps ([`VddConfig::chunks`]): the same student, bit for bit, for any number
//! of threads and whether the teacher forks or not; the chunks' gradient is the batch's.

use super::tests::small_run;
use super::*;
use crate::test_support::IsoGmm;
use faer::MatMut;

/// [`IsoGmm`] that forks, so that the chunks run on the worker threads.
#[derive(Clone)]
struct Forking(IsoGmm);

impl ScoreModel for Forking {
    fn action_dim(&self) -> usize {
        self.0.action_dim()
    }
    fn state_dim(&self) -> usize {
        self.0.state_dim()
    }
    fn score(
        &mut self,
        a: MatRef<'_, f32>,
        s: MatRef<'_, f32>,
        sigma: &[f32],
        out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        self.0.score(a, s, sigma, out)
    }
    fn sample_actions(
        &mut self,
        s: MatRef<'_, f32>,
        rng: &mut dyn rand::RngCore,
        out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        self.0.sample_actions(s, rng, out)
    }
    fn fork(&self) -> Option<Box<dyn ScoreModel + Send>> {
        Some(Box::new(self.clone()))
    }
}

thread_local! {
    /// The runs' [`VddConfig::experts_per_state`], per test thread.
    static SUBSET: std::cell::Cell<Option<usize>> = const { std::cell::Cell::new(None) };
}

/// Runs `check` with every expert trained at every state, then with two of the four.
fn with_and_without_subsets(check: impl Fn()) {
    for k in [None, Some(2)] {
        SUBSET.with(|s| s.set(k));
        check();
    }
    SUBSET.with(|s| s.set(None));
}

fn values(p: &dyn Parameters) -> Vec<f32> {
    let mut out = Vec::new();
    p.visit_params("", &mut |_, p| out.extend_from_slice(&p.value));
    out
}

/// Trains `iterations` of the small run (two expert steps per iteration when `iterations > 1`)
/// with `chunks` chunks on `threads` threads, the score taken at `score_at` (noised samples at
/// levels in `[0.2, 0.6]`) and [`SUBSET`]'s experts per state; returns the student's
/// parameters, every iteration's metrics and the last expert gradient.
fn run<S: ScoreModel>(
    teacher: S,
    chunks: usize,
    threads: usize,
    iterations: usize,
    score_at: ScoreAt,
) -> (Vec<f32>, Vec<IterationMetrics>, Vec<f32>) {
    let (mut config, _, student, data) = small_run(iterations);
    if score_at == ScoreAt::NoisedSample {
        config.score_at = score_at;
        config.noise = vdd_core::NoiseSchedule::Uniform { min: 0.2, max: 0.6 };
    }
    config.chunks = chunks;
    config.experts_per_state = SUBSET.with(|k| k.get());
    config.expert_steps_per_iter = if iterations > 1 { 2 } else { 1 };
    config.expert_weighting = ExpertWeighting::Gating;
    let mut vdd = Vdd::new(config, teacher, student, data).unwrap();
    vdd.set_threads(threads).unwrap();
    let mut metrics = Vec::new();
    vdd.train(|m| metrics.push(*m)).unwrap();
    let mut grad = Vec::new();
    vdd.student_mut().expert_networks_mut().visit_params("", &mut |_, p| {
        grad.extend_from_slice(&p.grad);
    });
    (values(vdd.student()), metrics, grad)
}

#[test]
fn chunked_students_do_not_depend_on_the_threads() {
    with_and_without_subsets(|| {
        for score_at in [ScoreAt::CleanSample, ScoreAt::NoisedSample] {
            chunked_students_do_not_depend_on_the_threads_with(score_at);
        }
    });
}

fn chunked_students_do_not_depend_on_the_threads_with(at: ScoreAt) {
    let teacher = IsoGmm::circle(4, 2.0, 0.5);
    // Batches of 8 states in 3 chunks (3, 3 and 2 states).
    let one = run(Forking(teacher.clone()), 3, 1, 15, at);
    for threads in [0, 2, 3] {
        assert!(one == run(Forking(teacher.clone()), 3, threads, 15, at), "{threads} threads");
    }
    // A teacher that does not fork is queried for each chunk in turn: the same student.
    assert!(one == run(teacher.clone(), 3, 2, 15, at));
    // One chunk is the unchunked step, whatever the threads.
    assert!(run(teacher.clone(), 1, 1, 15, at) == run(Forking(teacher), 1, 2, 15, at));
}

#[test]
fn the_chunks_gradient_is_the_batch_gradient() {
    with_and_without_subsets(|| {
        for score_at in [ScoreAt::CleanSample, ScoreAt::NoisedSample] {
            the_chunks_gradient_is_the_batch_gradient_with(score_at);
        }
    });
}

fn the_chunks_gradient_is_the_batch_gradient_with(at: ScoreAt) {
    // After one iteration from the same start, the chunked and the unchunked gradients differ
    // only by the order of the sums over states.
    let teacher = Forking(IsoGmm::circle(4, 2.0, 0.5));
    let (_, m1, g1) = run(teacher.clone(), 1, 1, 1, at);
    let (_, m4, g4) = run(teacher, 4, 2, 1, at);
    assert_eq!(g1.len(), g4.len());
    let scale = g1.iter().fold(0.0f32, |m, g| m.max(g.abs()));
    for (a, b) in g1.iter().zip(&g4) {
        assert!((a - b).abs() <= 1e-4 * scale, "{a} vs {b}");
    }
    let (e1, e4) = (m1[0].expert, m4[0].expert);
    assert_eq!(e1.noise_level, e4.noise_level);
    assert!((e1.corrected_score_rms - e4.corrected_score_rms).abs() < 1e-5);
    assert!((e1.log_responsibility - e4.log_responsibility).abs() < 1e-5);
    assert!((m1[0].gating_entropy - m4[0].gating_entropy).abs() < 1e-5);
}
