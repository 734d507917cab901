//! The expert steps with the state batch split into [`VddConfig::chunks`] chunks, run on the
//! trainer's [`Workers`] ([`vdd_nn::parallel`]).
//!
//! Each chunk holds a replica of the student (the live parameters copied in before every
//! step), a fork of the teacher ([`ScoreModel::fork`]) and the buffers of its states: the E-step
//! snapshot, the samples, the teacher's scores, the moments and the student's backward pass.
//! The `ε` and noise levels of the whole batch are drawn first in the calling thread, in the
//! order of the unchunked step; the chunks' gradients are then summed in chunk order. So the
//! student is the same bits for any number of threads. A teacher that does not fork is queried
//! for every chunk in turn in the calling thread, with the same results.

use faer::MatRef;
use vdd_core::{Expert, ScoreModel};
use vdd_moe::{Moe, MoeOutput};
use vdd_nn::Parameters;
use vdd_nn::parallel::{add_grads, chunk_range, copy_values};

use super::subset::expert_subset;
use super::{Vdd, at_iteration, e_step_weights};
use crate::both_sides::BothSides;
use crate::config::ExpertWeighting;
use crate::error::VddError;
use crate::expert_step::{
    ExpertStepBuffers, ExpertStepStats, ExpertSubset, MomentSums, moments_from_noise,
    raw_gradients_of_chunk,
};
use crate::spaces::{ActionMap, with_map};

/// One chunk of the state batch: its fork of the teacher and its work.
pub(super) struct Chunk<E: Expert> {
    /// The chunk's copy of the teacher; `None` when the teacher does not fork (or before the
    /// first step).
    teacher: Option<Box<dyn ScoreModel + Send>>,
    work: ChunkWork<E>,
}

/// A chunk's replica of the student and its buffers.
struct ChunkWork<E: Expert> {
    student: Moe<E>,
    snapshot: MoeOutput,
    weights: Vec<f32>,
    buf: ExpertStepBuffers,
    map_scratch: Vec<f32>,
    flat: Vec<f32>,
    sums: MomentSums,
    /// `−Σ q(z|s) log q(z|s)` over the chunk's states (E-step).
    entropy_sum: f32,
    result: Result<(), VddError>,
}

/// What every chunk of one expert step reads.
struct StepInputs<'a, E: Expert> {
    /// The live student, whose parameters each replica copies.
    master: &'a Moe<E>,
    /// The whole batch in the student's and in the teacher's space.
    states: MatRef<'a, f32>,
    teacher_states: MatRef<'a, f32>,
    /// `ε` and noise levels of the whole batch.
    eps: &'a [f32],
    levels: &'a [f32],
    /// The noising with noise on both sides.
    both: Option<&'a BothSides>,
    /// The experts each state of the whole batch trains (`None`: all of them).
    subset: Option<ExpertSubset<'a>>,
    action_map: Option<&'a ActionMap>,
    weighting: ExpertWeighting,
    vi_samples: usize,
    chunks: usize,
    /// The first expert step of the iteration: the replicas take the E-step snapshot.
    first: bool,
    iteration: usize,
}

impl<E: Expert> Chunk<E> {
    /// A chunk with a replica of `student`; the teacher is forked at the first step.
    pub(super) fn new(student: &Moe<E>) -> Self {
        Self {
            teacher: None,
            work: ChunkWork {
                student: student.clone(),
                snapshot: MoeOutput::default(),
                weights: Vec::new(),
                buf: ExpertStepBuffers::default(),
                map_scratch: Vec::new(),
                flat: Vec::new(),
                sums: MomentSums::default(),
                entropy_sum: 0.0,
                result: Ok(()),
            },
        }
    }

    /// Drops the fork of the teacher (the teacher may have changed); the next step forks again.
    pub(super) fn forget_teacher(&mut self) {
        self.teacher = None;
    }
}

impl<E: Expert> ChunkWork<E> {
    /// Chunk `c`'s part of one expert step: the replica's forward pass (and, at the first step,
    /// the E-step snapshot), the samples and teacher scores, the moments and the replica's
    /// gradient of the batch's loss.
    fn run(&mut self, c: usize, inp: &StepInputs<'_, E>, teacher: &mut dyn ScoreModel) {
        self.result = self.try_run(c, inp, teacher);
    }

    fn try_run(
        &mut self,
        c: usize,
        inp: &StepInputs<'_, E>,
        teacher: &mut dyn ScoreModel,
    ) -> Result<(), VddError> {
        let b_n = inp.states.nrows();
        let rows = chunk_range(b_n, inp.chunks, c);
        let (start, len) = (rows.start, rows.len());
        copy_values(inp.master, &mut self.student, &mut self.flat);
        let states = inp.states.subrows(start, len);
        let z_n = self.student.num_experts();
        if inp.first {
            self.student.forward(states)?;
            self.snapshot.clone_from(self.student.output());
            let log_gating = &self.snapshot.log_gating;
            self.entropy_sum = e_step_weights(log_gating, inp.weighting, z_n, &mut self.weights);
        } else {
            self.student.forward_experts(states)?;
        }
        let subset = inp.subset.map(|s| s.states(start..start + len));
        let per_state = subset.map_or(z_n, |s| s.per_state) * inp.vi_samples;
        let d = self.student.config().action_dim;
        let samples = start * per_state..(start + len) * per_state;
        self.buf.eps.clear();
        self.buf.eps.extend_from_slice(&inp.eps[samples.start * d..samples.end * d]);
        self.buf.noise_levels.clear();
        self.buf.noise_levels.extend_from_slice(&inp.levels[samples]);
        let teacher_states = inp.teacher_states.subrows(start, len);
        let (out, snapshot, v) = (self.student.output(), &self.snapshot, inp.vi_samples);
        let both = inp.both.map(|b| b.view(start..start + len, per_state, d));
        let buf = &mut self.buf;
        let sums = with_map(teacher, inp.action_map, &mut self.map_scratch, |teacher| {
            moments_from_noise(teacher, out, snapshot, teacher_states, v, both, subset, buf)
        });
        self.sums = sums.map_err(at_iteration(inp.iteration))?;
        let (expert, out) = (self.student.expert(), self.student.output());
        raw_gradients_of_chunk(expert, out, &self.weights, b_n, subset, &mut self.buf);
        self.student.expert_networks_mut().zero_grad();
        self.student.backward_experts(&self.buf.grad_raw)?;
        Ok(())
    }
}

impl<S: ScoreModel, E: Expert> Vdd<S, E> {
    /// The expert steps of iteration `it` on the chunks (see the module docs); returns the
    /// last step's statistics, the mean gating entropy of the batch and the last learning
    /// rate. The E-step snapshot is taken by the replicas at the first step.
    pub(super) fn chunked_expert_steps(
        &mut self,
        it: usize,
        progress: f32,
    ) -> Result<(ExpertStepStats, f32, f32), VddError> {
        if self.chunks.iter().any(|c| c.teacher.is_none()) {
            for chunk in &mut self.chunks {
                chunk.teacher = self.teacher.fork();
            }
        }
        let parallel = self.chunks.iter().all(|c| c.teacher.is_some());
        let (b_n, z_n, v_n) =
            (self.config.batch_size, self.student.num_experts(), self.config.vi_samples);
        let (mut stats, mut gating_entropy, mut expert_lr) = (ExpertStepStats::default(), 0.0, 0.0);
        for k in 0..self.config.expert_steps_per_iter {
            let stream = (it * self.config.expert_steps_per_iter + k) as u64;
            let mut rng = self.seeds.stream_indexed("vi-noise", stream);
            self.draw_subset(stream);
            let noised = self.draw_noise(progress, &mut rng).map_err(at_iteration(it))?;
            let inputs = StepInputs {
                master: &self.student,
                states: self.batch.as_ref(),
                teacher_states: match &self.teacher_states {
                    Some(_) => self.teacher_batch.as_ref(),
                    None => self.batch.as_ref(),
                },
                eps: &self.buf.eps,
                levels: &self.buf.noise_levels,
                both: noised.then_some(&self.both),
                subset: expert_subset(&self.subset, self.slots()),
                action_map: self.action_map.as_ref(),
                weighting: self.config.expert_weighting,
                vi_samples: v_n,
                chunks: self.chunks.len(),
                first: k == 0,
                iteration: it,
            };
            if parallel {
                self.workers.for_each_mut(&mut self.chunks, |c, chunk| {
                    let teacher = chunk.teacher.as_deref_mut().expect("forked above");
                    chunk.work.run(c, &inputs, teacher);
                });
            } else {
                for (c, chunk) in self.chunks.iter_mut().enumerate() {
                    chunk.work.run(c, &inputs, &mut self.teacher);
                }
            }
            let mut sums = MomentSums::default();
            let nets = self.student.expert_networks_mut();
            nets.zero_grad();
            if k == 0 {
                gating_entropy = 0.0;
            }
            for chunk in &mut self.chunks {
                std::mem::replace(&mut chunk.work.result, Ok(()))?;
                sums.add(&chunk.work.sums);
                if k == 0 {
                    gating_entropy += chunk.work.entropy_sum;
                }
                add_grads(chunk.work.student.expert_networks_mut(), nets, &mut self.flat);
            }
            stats = sums.stats(&self.buf.noise_levels, b_n * z_n);
            expert_lr = self.expert_update(it)?;
        }
        Ok((stats, gating_entropy / b_n as f32, expert_lr))
    }
}
