//! Evaluating a mixture on every pair of a dataset: the E-step of EM and IMC (both variants)
//! and their log-likelihood metric. [`evaluate_dataset`] runs in the calling thread;
//! [`ParallelEval`] splits the same work over the cores with the same bits.
//!
//! Both run the mixture on blocks of [`EVAL_CHUNK`] rows that start at multiples of
//! [`EVAL_CHUNK`], score each row from its block's output, and sum the rows' log-likelihoods
//! in row order. The parallel path gives each worker a replica of the mixture and a run of
//! whole blocks, so every block is computed exactly as in one thread and the sum is the same:
//! the number of threads never changes a result.

use std::ops::Range;

use vdd_core::{Expert, check_len, gaussian};
use vdd_moe::Moe;
use vdd_nn::Parameters;
use vdd_nn::parallel::{Workers, chunk_range, copy_values};

use super::EVAL_CHUNK;
use crate::dataset::Dataset;
use crate::error::MixtureError;

/// Evaluates the mixture on every pair of `data` (in chunks of [`EVAL_CHUNK`] rows) and returns
/// the mean log-likelihood `(1/n) Σ_o log q(a_o|s_o)`.
///
/// Optionally writes the experts' log-likelihoods `log N(a_o; μ_z(s_o), Σ_z(s_o))` into
/// `expert_log_lik` and the responsibilities `q(z|a_o, s_o)` into `responsibilities` (both
/// `n·Z`, row-major).
pub fn evaluate_dataset<E: Expert>(
    student: &mut Moe<E>,
    data: &Dataset,
    expert_log_lik: Option<&mut [f32]>,
    responsibilities: Option<&mut [f32]>,
) -> Result<f64, MixtureError> {
    check_outputs(student, data, expert_log_lik.as_deref(), responsibilities.as_deref())?;
    let mut log_q = vec![0.0f32; data.len()];
    let outputs = (expert_log_lik, responsibilities);
    score_rows(Scoring::Gaussian, student, data, 0..data.len(), outputs, &mut log_q)?;
    Ok(mean_in_order(&log_q))
}

/// How the experts score a pair.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Scoring {
    /// `ℓ_z = log N(a; μ_z, Σ_z)` (EM, the paper's IMC).
    Gaussian,
    /// The authors' IMC: `ℓ_z = −½‖a − μ_z‖²`, and the mixture's log-likelihood with experts
    /// `N(μ_z, I)`.
    UnitVariance,
}

/// Checks the data's dimensions and the outputs' lengths against the mixture.
fn check_outputs<E: Expert>(
    student: &Moe<E>,
    data: &Dataset,
    expert_log_lik: Option<&[f32]>,
    responsibilities: Option<&[f32]>,
) -> Result<(), MixtureError> {
    let (n, z_n) = (data.len(), student.num_experts());
    data.check_dims(student.config().state_dim, student.config().action_dim)?;
    if let Some(e) = expert_log_lik {
        check_len("expert log-likelihood output", e.len(), n * z_n)?;
    }
    if let Some(r) = responsibilities {
        check_len("responsibilities output", r.len(), n * z_n)?;
    }
    Ok(())
}

/// `(1/n) Σ_o x_o`, summed in `f64` in row order.
fn mean_in_order(xs: &[f32]) -> f64 {
    xs.iter().map(|&x| f64::from(x)).sum::<f64>() / xs.len() as f64
}

/// Scores the pairs `rows` of `data` (`rows.start` a multiple of [`EVAL_CHUNK`]) in blocks of
/// [`EVAL_CHUNK`] rows: each row's `log q(a|s)` into `log_q`, and optionally the experts'
/// log-likelihoods and the responsibilities, all indexed from `rows.start`.
fn score_rows<E: Expert>(
    scoring: Scoring,
    student: &mut Moe<E>,
    data: &Dataset,
    rows: Range<usize>,
    outputs: (Option<&mut [f32]>, Option<&mut [f32]>),
    log_q: &mut [f32],
) -> Result<(), MixtureError> {
    let (mut expert_log_lik, mut responsibilities) = outputs;
    let (z_n, d) = (student.num_experts(), student.config().action_dim);
    let constant = 0.5 * d as f32 * gaussian::LN_2PI;
    let (mut a, mut work, mut row) = (vec![0.0f32; d], vec![0.0f32; d], vec![0.0f32; z_n]);
    let actions = data.actions();
    let mut start = rows.start;
    while start < rows.end {
        let len = EVAL_CHUNK.min(rows.end - start);
        student.forward(data.states().subrows(start, len))?;
        let out = student.output();
        for b in 0..len {
            let (o, i) = (start + b, start + b - rows.start);
            for (j, a) in a.iter_mut().enumerate() {
                *a = actions[(o, j)];
            }
            let lg = out.log_gating_row(b);
            for k in 0..z_n {
                let ll = match scoring {
                    Scoring::Gaussian => {
                        let ll =
                            gaussian::log_density(&a, out.mean(b, k), out.scale(b, k), &mut work);
                        row[k] = lg[k] + ll;
                        ll
                    }
                    Scoring::UnitVariance => {
                        let mean = out.mean(b, k);
                        let sq: f32 = (0..d).map(|j| (a[j] - mean[j]).powi(2)).sum();
                        row[k] = lg[k] - 0.5 * sq - constant;
                        -0.5 * sq
                    }
                };
                if let Some(e) = expert_log_lik.as_deref_mut() {
                    e[i * z_n + k] = ll;
                }
            }
            log_q[i] = gaussian::softmax_in_place(&mut row);
            if let Some(r) = responsibilities.as_deref_mut() {
                r[i * z_n..(i + 1) * z_n].copy_from_slice(&row);
            }
        }
        start += len;
    }
    Ok(())
}

/// [`evaluate_dataset`] on all cores, with the same results bit for bit (module docs). Keeps a
/// replica of the mixture per worker between calls; a replica takes the mixture's parameter
/// values at every call, and is cloned afresh when the mixture's configuration changed.
pub(crate) struct ParallelEval<E: Expert> {
    workers: Workers,
    replicas: Vec<Moe<E>>,
    flat: Vec<f32>,
    log_q: Vec<f32>,
}

/// One worker's share: a replica, a run of whole blocks and that run's outputs.
struct Part<'a, E: Expert> {
    replica: &'a mut Moe<E>,
    rows: Range<usize>,
    expert_log_lik: Option<&'a mut [f32]>,
    responsibilities: Option<&'a mut [f32]>,
    log_q: &'a mut [f32],
    result: Result<(), MixtureError>,
}

impl<E: Expert> ParallelEval<E> {
    /// Evaluation on `workers`.
    pub(crate) fn new(workers: Workers) -> Self {
        Self { workers, replicas: Vec::new(), flat: Vec::new(), log_q: Vec::new() }
    }

    /// As [`evaluate_dataset`], with the experts' `scoring`; runs in the calling thread when
    /// there is one worker or one block.
    pub(crate) fn evaluate(
        &mut self,
        scoring: Scoring,
        student: &mut Moe<E>,
        data: &Dataset,
        mut expert_log_lik: Option<&mut [f32]>,
        mut responsibilities: Option<&mut [f32]>,
    ) -> Result<f64, MixtureError> {
        check_outputs(student, data, expert_log_lik.as_deref(), responsibilities.as_deref())?;
        let (n, z_n) = (data.len(), student.num_experts());
        let blocks = n.div_ceil(EVAL_CHUNK);
        let parts = self.workers.threads().min(blocks);
        self.log_q.resize(n, 0.0);
        if parts <= 1 {
            let outputs = (expert_log_lik, responsibilities);
            score_rows(scoring, student, data, 0..n, outputs, &mut self.log_q)?;
            return Ok(mean_in_order(&self.log_q));
        }
        self.sync_replicas(student, parts);
        let mut log_q = self.log_q.as_mut_slice();
        let mut shares = Vec::with_capacity(parts);
        for (p, replica) in self.replicas.iter_mut().enumerate().take(parts) {
            let b = chunk_range(blocks, parts, p);
            let rows = b.start * EVAL_CHUNK..(b.end * EVAL_CHUNK).min(n);
            let len = rows.len();
            let (head, rest) = std::mem::take(&mut log_q).split_at_mut(len);
            log_q = rest;
            shares.push(Part {
                replica,
                rows,
                expert_log_lik: take_rows(&mut expert_log_lik, len * z_n),
                responsibilities: take_rows(&mut responsibilities, len * z_n),
                log_q: head,
                result: Ok(()),
            });
        }
        self.workers.for_each_mut(&mut shares, |_, s| {
            let outputs = (s.expert_log_lik.as_deref_mut(), s.responsibilities.as_deref_mut());
            s.result = score_rows(scoring, s.replica, data, s.rows.clone(), outputs, s.log_q);
        });
        for s in shares {
            s.result?;
        }
        Ok(mean_in_order(&self.log_q))
    }

    /// At least `parts` replicas with the mixture's configuration; the first `parts` take its
    /// parameter values (the rest are used only once a call needs them, and take them then).
    fn sync_replicas(&mut self, student: &Moe<E>, parts: usize) {
        let stale =
            |r: &Moe<E>| r.config() != student.config() || r.num_params() != student.num_params();
        if self.replicas.iter().any(stale) {
            self.replicas.clear();
        }
        while self.replicas.len() < parts {
            self.replicas.push(student.clone());
        }
        for r in self.replicas.iter_mut().take(parts) {
            copy_values(student, r, &mut self.flat);
        }
    }
}

/// Splits the first `len` values off an optional output.
fn take_rows<'a>(out: &mut Option<&'a mut [f32]>, len: usize) -> Option<&'a mut [f32]> {
    let rest = out.take()?;
    let (head, tail) = rest.split_at_mut(len);
    *out = Some(tail);
    Some(head)
}
