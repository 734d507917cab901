//! Denoising score matching: the seeded minibatch training loop shared by both teachers.

use std::time::Instant;

use faer::{Mat, MatRef};
use rand::Rng as _;
use serde::{Deserialize, Serialize};
use vdd_core::{Affine, Seeds};
use vdd_nn::parallel::{Workers, add_grads, chunk_range, copy_values};
use vdd_nn::{Adam, AdamConfig, LrSchedule, Parameters, clip_grad_norm};

use crate::error::{DiffusionError, Result};
use crate::net::{DenoiserNet, Ema};
use crate::normalize::{NormalizerKind, fit_normalizer};

/// Hyper-parameters of denoising-score-matching training.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainConfig {
    /// Optimisation steps.
    pub steps: u64,
    /// Minibatch size (clamped to the number of training pairs).
    pub batch_size: usize,
    /// Adam's hyper-parameters (`lr` is the peak learning rate).
    pub adam: AdamConfig,
    /// Linear learning-rate warm-up steps.
    pub warmup_steps: u64,
    /// After warm-up, the learning rate follows a cosine from 1 to this factor.
    pub final_lr_factor: f32,
    /// Decay of the exponential moving average of the weights used for sampling.
    pub ema_decay: f32,
    /// Global gradient-norm clipping threshold (`None`: no clipping).
    pub grad_clip: Option<f32>,
    /// Report progress every this many steps (and after the last step).
    pub log_every: u64,
    /// Chunks each minibatch is split into for the gradient (at most `MAX_CHUNKS` = 256): each
    /// chunk's forward and backward pass runs on its own replica of the network, possibly on
    /// another thread, and the chunks' gradients are summed in chunk order
    /// ([`vdd_nn::parallel`]). The results depend on the number of chunks, never on the number
    /// of threads ([`crate::TeacherTrainer::set_threads`]); with one chunk (the default) the
    /// whole batch runs in the calling thread.
    #[serde(default = "one_chunk")]
    pub chunks: usize,
}

/// Largest [`TrainConfig::chunks`].
pub const MAX_CHUNKS: usize = 256;

fn one_chunk() -> usize {
    1
}

impl Default for TrainConfig {
    fn default() -> Self {
        Self {
            steps: 10_000,
            batch_size: 256,
            adam: AdamConfig { lr: 1e-3, ..Default::default() },
            warmup_steps: 100,
            final_lr_factor: 0.05,
            ema_decay: 0.999,
            grad_clip: Some(1.0),
            log_every: 500,
            chunks: 1,
        }
    }
}

impl TrainConfig {
    /// Checks the numbers.
    pub fn validate(&self) -> Result<()> {
        let c = &self.adam;
        let ok = self.steps > 0
            && self.batch_size > 0
            && c.lr.is_finite()
            && c.lr > 0.0
            && (0.0..1.0).contains(&c.beta1)
            && (0.0..1.0).contains(&c.beta2)
            && c.eps > 0.0
            && c.weight_decay.is_finite()
            && c.weight_decay >= 0.0
            && self.final_lr_factor.is_finite()
            && self.final_lr_factor >= 0.0
            && (0.0..1.0).contains(&self.ema_decay)
            && self.grad_clip.is_none_or(|g| g.is_finite() && g > 0.0)
            && self.log_every > 0
            && (1..=MAX_CHUNKS).contains(&self.chunks);
        if ok {
            Ok(())
        } else {
            Err(DiffusionError::Config(format!("invalid training configuration {self:?}")))
        }
    }

    /// The learning-rate schedule over the run of [`TrainConfig::steps`] steps.
    fn lr_schedule(&self) -> LrSchedule {
        let cosine = LrSchedule::Cosine { final_factor: self.final_lr_factor };
        if self.warmup_steps > 0 {
            LrSchedule::Warmup { warmup_steps: self.warmup_steps, then: Box::new(cosine) }
        } else {
            cosine
        }
    }
}

/// A progress report from training, passed to the caller's callback.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TrainProgress {
    /// Steps done so far.
    pub step: u64,
    /// Total steps.
    pub total_steps: u64,
    /// Mean denoising loss over the steps since the previous report.
    pub loss: f32,
    /// Learning rate of the last step.
    pub lr: f32,
    /// Wall-clock seconds since training started.
    pub elapsed_secs: f64,
}

/// Training data after validation and normalisation.
pub(crate) struct PreparedData {
    pub state_norm: Affine,
    pub action_norm: Affine,
    pub states: Mat<f32>,
    pub actions: Mat<f32>,
}

/// Validates `states` (`n x d_s`) and `actions` (`n x d_a`), fits the normalisers and returns
/// normalised copies.
pub(crate) fn prepare_data(
    states: MatRef<'_, f32>,
    actions: MatRef<'_, f32>,
    state_kind: NormalizerKind,
    action_kind: NormalizerKind,
) -> Result<PreparedData> {
    let n = actions.nrows();
    if n == 0 {
        return Err(DiffusionError::Data("no training pairs".into()));
    }
    if actions.ncols() == 0 {
        return Err(DiffusionError::Data("actions have zero columns".into()));
    }
    if states.nrows() != n {
        return Err(DiffusionError::Data(format!(
            "{} state rows but {n} action rows",
            states.nrows()
        )));
    }
    vdd_core::check_finite("training states", states)?;
    vdd_core::check_finite("training actions", actions)?;
    let state_norm = fit_normalizer(states, state_kind);
    let action_norm = fit_normalizer(actions, action_kind);
    Ok(PreparedData {
        states: state_norm.normalize_rows(states)?,
        actions: action_norm.normalize_rows(actions)?,
        state_norm,
        action_norm,
    })
}

/// One row's denoising-score-matching coefficients at a noise level: the network sees
/// `x = input_a · a + input_eps · ε` with noise condition `c_noise` and regresses
/// `target_a · a + target_eps · ε`.
///
/// DDPM (`ε`-prediction): `x = sqrt(ᾱ) a + sqrt(1 − ᾱ) ε`, target `ε`. EDM: the network input
/// is `c_in (a + σ ε)` and the target `(a − c_skip (a + σ ε))/c_out`, both linear in `a` and
/// `ε`; the plain squared error then equals EDM's `λ(σ) ||D − a||²`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DsmRow {
    /// The network's noise condition.
    pub c_noise: f32,
    /// Coefficient of the clean action in the network input.
    pub input_a: f32,
    /// Coefficient of the noise in the network input.
    pub input_eps: f32,
    /// Coefficient of the clean action in the regression target.
    pub target_a: f32,
    /// Coefficient of the noise in the regression target.
    pub target_eps: f32,
}

/// The training noise of a diffusion process: how levels are drawn and what the network
/// regresses at a level.
pub trait DsmNoise {
    /// One training noise level.
    fn draw_level(&self, rng: &mut dyn rand::RngCore) -> f32;
    /// The regression at `level`.
    fn dsm_row(&self, level: f32) -> DsmRow;
}

/// Buffers of the denoising-score-matching loss `mean ||F(x, s, c_noise) − target||²` shared
/// by both teachers.
#[derive(Debug, Clone)]
pub(crate) struct Dsm {
    rows: Vec<DsmRow>,
    c_noise: Vec<f32>,
    eps: Mat<f32>,
    x: Mat<f32>,
    grad: Mat<f32>,
}

impl Default for Dsm {
    fn default() -> Self {
        Self {
            rows: Vec::new(),
            c_noise: Vec::new(),
            eps: Mat::zeros(0, 0),
            x: Mat::zeros(0, 0),
            grad: Mat::zeros(0, 0),
        }
    }
}

impl Dsm {
    /// Draws the noise levels (one per row) and then the Gaussian noise for a batch of `n`
    /// rows of `d` dimensions.
    pub(crate) fn draw(
        &mut self,
        noise: &impl DsmNoise,
        n: usize,
        d: usize,
        rng: &mut vdd_core::Rng,
    ) {
        self.rows.clear();
        self.c_noise.clear();
        for _ in 0..n {
            let row = noise.dsm_row(noise.draw_level(rng));
            self.rows.push(row);
            self.c_noise.push(row.c_noise);
        }
        if self.eps.nrows() != n || self.eps.ncols() != d {
            self.eps = Mat::zeros(n, d);
            self.x = Mat::zeros(n, d);
            self.grad = Mat::zeros(n, d);
        }
        for j in 0..d {
            vdd_core::fill_standard_normal(rng, self.eps.col_as_slice_mut(j));
        }
    }

    /// The loss on a batch with the drawn noise; with `backward`, accumulates its parameter
    /// gradients into `net`.
    pub(crate) fn loss(
        &mut self,
        net: &mut DenoiserNet,
        actions: MatRef<'_, f32>,
        states: MatRef<'_, f32>,
        backward: bool,
    ) -> f32 {
        let (n, d) = (actions.nrows(), actions.ncols());
        let scale = 1.0 / (n * d) as f32;
        let (rows, c_noise, eps) = (&self.rows[..], &self.c_noise[..], self.eps.as_ref());
        let io = DsmBuffers { x: &mut self.x, grad: &mut self.grad };
        let total =
            dsm_rows(net, DsmInputs { rows, c_noise, eps, actions, states }, io, scale, backward);
        (total * f64::from(scale)) as f32
    }

    /// The rows `range` of the drawn batch (`actions`, `states` of the whole batch) on `chunk`:
    /// the sum of the squared residuals, and the gradient of `scale ·` that sum accumulated into
    /// the chunk's network.
    fn chunk_total(
        &self,
        chunk: &mut DsmChunk,
        range: std::ops::Range<usize>,
        actions: MatRef<'_, f32>,
        states: MatRef<'_, f32>,
        scale: f32,
    ) -> f64 {
        let (start, len) = (range.start, range.len());
        let inputs = DsmInputs {
            rows: &self.rows[range.clone()],
            c_noise: &self.c_noise[range],
            eps: self.eps.as_ref().subrows(start, len),
            actions: actions.subrows(start, len),
            states: states.subrows(start, len),
        };
        let io = DsmBuffers { x: &mut chunk.x, grad: &mut chunk.grad };
        dsm_rows(&mut chunk.net, inputs, io, scale, true)
    }
}

/// The drawn noise and data of some rows of a batch.
struct DsmInputs<'a> {
    rows: &'a [DsmRow],
    c_noise: &'a [f32],
    eps: MatRef<'a, f32>,
    actions: MatRef<'a, f32>,
    states: MatRef<'a, f32>,
}

/// The network input and output gradient buffers of some rows (resized when needed).
struct DsmBuffers<'a> {
    x: &'a mut Mat<f32>,
    grad: &'a mut Mat<f32>,
}

/// The denoising loss of some rows: returns the sum of their squared residuals and, with
/// `backward`, accumulates the gradient of `scale ·` that sum into `net`.
fn dsm_rows(
    net: &mut DenoiserNet,
    inp: DsmInputs<'_>,
    io: DsmBuffers<'_>,
    scale: f32,
    backward: bool,
) -> f64 {
    let (n, d) = (inp.actions.nrows(), inp.actions.ncols());
    if io.x.nrows() != n || io.x.ncols() != d {
        *io.x = Mat::zeros(n, d);
        *io.grad = Mat::zeros(n, d);
    }
    for j in 0..d {
        let x = io.x.col_as_slice_mut(j);
        for i in 0..n {
            let r = &inp.rows[i];
            x[i] = r.input_a * inp.actions[(i, j)] + r.input_eps * inp.eps[(i, j)];
        }
    }
    let f = net.forward(io.x.as_ref(), inp.states, inp.c_noise);
    let mut total = 0.0f64;
    for j in 0..d {
        let g = io.grad.col_as_slice_mut(j);
        for i in 0..n {
            let row = &inp.rows[i];
            let target = row.target_a * inp.actions[(i, j)] + row.target_eps * inp.eps[(i, j)];
            let r = f[(i, j)] - target;
            total += f64::from(r * r);
            g[i] = 2.0 * r * scale;
        }
    }
    if backward {
        net.backward(io.grad.as_ref());
    }
    total
}

/// One chunk of a minibatch ([`TrainConfig::chunks`]): a replica of the network and its
/// buffers, and the chunk's sum of squared residuals.
struct DsmChunk {
    net: DenoiserNet,
    x: Mat<f32>,
    grad: Mat<f32>,
    flat: Vec<f32>,
    total: f64,
}

fn gather_rows(src: &Mat<f32>, idx: &[usize], dst: &mut Mat<f32>) {
    for j in 0..src.ncols() {
        let s = src.col_as_slice(j);
        let d = dst.col_as_slice_mut(j);
        for (o, &i) in d.iter_mut().zip(idx) {
            *o = s[i];
        }
    }
}

/// The denoising-score-matching loop on normalised data, one optimiser step at a time: Adam
/// on the live network, the EMA network for sampling.
pub(crate) struct DsmLoop {
    config: TrainConfig,
    data: PreparedData,
    net: DenoiserNet,
    ema_net: DenoiserNet,
    ema: Ema,
    dsm: Dsm,
    adam: Adam,
    schedule: LrSchedule,
    batch_rng: vdd_core::Rng,
    noise_rng: vdd_core::Rng,
    order: Vec<usize>,
    cursor: usize,
    idx: Vec<usize>,
    a_batch: Mat<f32>,
    s_batch: Mat<f32>,
    loss_sum: f64,
    loss_count: u64,
    start: Instant,
    step: u64,
    chunks: Vec<DsmChunk>,
    workers: Workers,
    flat: Vec<f32>,
}

impl DsmLoop {
    /// Starts training `net` on `data` with the `"minibatch"` and `"dsm-noise"` streams of
    /// `seeds`.
    pub(crate) fn new(
        net: DenoiserNet,
        config: &TrainConfig,
        data: PreparedData,
        seeds: &Seeds,
    ) -> Result<Self> {
        config.validate()?;
        let n = data.actions.nrows();
        let (da, ds) = (data.actions.ncols(), data.states.ncols());
        let b = config.batch_size.min(n);
        let chunks = match config.chunks.min(b) {
            1 => Vec::new(),
            c => (0..c)
                .map(|_| DsmChunk {
                    net: net.clone(),
                    x: Mat::zeros(0, 0),
                    grad: Mat::zeros(0, 0),
                    flat: Vec::new(),
                    total: 0.0,
                })
                .collect(),
        };
        Ok(Self {
            chunks,
            workers: Workers::default(),
            flat: Vec::new(),
            ema_net: net.clone(),
            net,
            ema: Ema::new(config.ema_decay),
            dsm: Dsm::default(),
            adam: Adam::new(config.adam),
            schedule: config.lr_schedule(),
            batch_rng: seeds.stream("minibatch"),
            noise_rng: seeds.stream("dsm-noise"),
            order: (0..n).collect(),
            cursor: n, // forces a shuffle before the first batch
            idx: vec![0usize; b],
            a_batch: Mat::<f32>::zeros(b, da),
            s_batch: Mat::<f32>::zeros(b, ds),
            loss_sum: 0.0,
            loss_count: 0,
            start: Instant::now(),
            step: 0,
            config: config.clone(),
            data,
        })
    }

    /// Runs the chunks of a step on `threads` threads ([`Workers::new`]; the default 0 is the
    /// process-wide pool). The results do not depend on it.
    pub(crate) fn set_threads(&mut self, threads: usize) -> Result<()> {
        self.workers = Workers::new(threads)?;
        Ok(())
    }

    /// Steps done so far.
    pub(crate) fn steps_done(&self) -> u64 {
        self.step
    }

    /// One optimiser step with the training noise of `noise`; returns a progress report every
    /// `log_every` steps and after the last. On error the step counter does not advance.
    pub(crate) fn step(&mut self, noise: &impl DsmNoise) -> Result<Option<TrainProgress>> {
        let (n, step) = (self.data.actions.nrows(), self.step);
        let da = self.data.actions.ncols();
        for slot in self.idx.iter_mut() {
            if self.cursor == n {
                // Fisher–Yates: one pass over the data per epoch, in a seeded order.
                for i in (1..n).rev() {
                    self.order.swap(i, self.batch_rng.random_range(0..=i));
                }
                self.cursor = 0;
            }
            *slot = self.order[self.cursor];
            self.cursor += 1;
        }
        gather_rows(&self.data.actions, &self.idx, &mut self.a_batch);
        gather_rows(&self.data.states, &self.idx, &mut self.s_batch);
        let b = self.idx.len();
        self.net.zero_grad();
        self.dsm.draw(noise, b, da, &mut self.noise_rng);
        let loss = if self.chunks.is_empty() {
            self.dsm.loss(&mut self.net, self.a_batch.as_ref(), self.s_batch.as_ref(), true)
        } else {
            // Each chunk on its replica (the live weights copied in), then the gradients
            // summed in chunk order: the same bits for any number of threads.
            let scale = 1.0 / (b * da) as f32;
            let (dsm, net, n_chunks) = (&self.dsm, &self.net, self.chunks.len());
            let (actions, states) = (self.a_batch.as_ref(), self.s_batch.as_ref());
            self.workers.for_each_mut(&mut self.chunks, |c, chunk| {
                copy_values(net, &mut chunk.net, &mut chunk.flat);
                chunk.net.zero_grad();
                let range = chunk_range(b, n_chunks, c);
                chunk.total = dsm.chunk_total(chunk, range, actions, states, scale);
            });
            let mut total = 0.0f64;
            for chunk in &self.chunks {
                add_grads(&chunk.net, &mut self.net, &mut self.flat);
                total += chunk.total;
            }
            (total * f64::from(scale)) as f32
        };
        if !loss.is_finite() {
            return Err(DiffusionError::Diverged { step: step + 1, loss });
        }
        if let Some(max) = self.config.grad_clip {
            let norm = clip_grad_norm(&mut self.net, max);
            if !norm.is_finite() {
                return Err(DiffusionError::Diverged { step: step + 1, loss: norm });
            }
        }
        let factor = self.schedule.factor(step, self.config.steps);
        self.adam.step(&mut self.net, factor)?;
        self.ema.update(&mut self.ema_net, &self.net);
        self.loss_sum += f64::from(loss);
        self.loss_count += 1;
        let done = step + 1;
        self.step = done;
        if done % self.config.log_every == 0 || done == self.config.steps {
            let report = TrainProgress {
                step: done,
                total_steps: self.config.steps,
                loss: (self.loss_sum / self.loss_count as f64) as f32,
                lr: self.config.adam.lr * factor,
                elapsed_secs: self.start.elapsed().as_secs_f64(),
            };
            self.loss_sum = 0.0;
            self.loss_count = 0;
            return Ok(Some(report));
        }
        Ok(None)
    }

    /// Ends training: the EMA network and the data (with its normalisers).
    pub(crate) fn finish(self) -> (DenoiserNet, PreparedData) {
        (self.ema_net, self.data)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bad_data_is_a_clear_error() {
        let s = Mat::<f32>::zeros(3, 1);
        let a = Mat::<f32>::zeros(3, 2);
        let k = NormalizerKind::Standard;
        assert!(prepare_data(s.as_ref(), a.as_ref(), k, k).is_ok());
        let e =
            prepare_data(Mat::<f32>::zeros(0, 1).as_ref(), Mat::<f32>::zeros(0, 2).as_ref(), k, k);
        assert!(matches!(e, Err(DiffusionError::Data(_))));
        let e = prepare_data(Mat::<f32>::zeros(2, 1).as_ref(), a.as_ref(), k, k);
        assert!(matches!(e, Err(DiffusionError::Data(_))));
        let e = prepare_data(s.as_ref(), Mat::<f32>::zeros(3, 0).as_ref(), k, k);
        assert!(matches!(e, Err(DiffusionError::Data(_))));
        let mut bad = a.clone();
        bad[(1, 1)] = f32::NAN;
        let e = prepare_data(s.as_ref(), bad.as_ref(), k, k);
        assert!(matches!(e, Err(DiffusionError::Core(vdd_core::CoreError::NonFinite { .. }))));
    }

    #[test]
    fn invalid_configs_are_rejected() {
        assert!(TrainConfig::default().validate().is_ok());
        for c in [
            TrainConfig { steps: 0, ..Default::default() },
            TrainConfig { batch_size: 0, ..Default::default() },
            TrainConfig { ema_decay: 1.0, ..Default::default() },
            TrainConfig { grad_clip: Some(0.0), ..Default::default() },
            TrainConfig {
                adam: AdamConfig { lr: f32::NAN, ..Default::default() },
                ..Default::default()
            },
        ] {
            assert!(c.validate().is_err(), "{c:?}");
        }
    }

    /// Trains a small BESO teacher with `chunks` chunks on `threads` threads; returns its EMA
    /// parameters and the reported losses.
    fn chunked_run(chunks: usize, threads: usize, steps: u64) -> (Vec<f32>, Vec<f32>) {
        use crate::{Beso, BesoConfig, NetConfig, TeacherTrainer};
        use vdd_core::Trainer;
        let states = Mat::from_fn(64, 1, |i, _| (i % 5) as f32);
        let actions = Mat::from_fn(64, 2, |i, j| ((i * 3 + j) % 7) as f32 / 3.0 - 1.0);
        let net = NetConfig { hidden_dim: 16, num_blocks: 1, ..Default::default() };
        let config = BesoConfig { net, ..Default::default() };
        let train =
            TrainConfig { steps, batch_size: 40, log_every: 1, chunks, ..Default::default() };
        let (s, a) = (states.as_ref(), actions.as_ref());
        let mut trainer = TeacherTrainer::new(&config, &train, s, a, 0).unwrap();
        trainer.set_threads(threads).unwrap();
        let mut losses = Vec::new();
        trainer.run(|r| losses.extend(r.map(|p| p.loss))).unwrap();
        let teacher: Beso = trainer.finish().unwrap();
        let mut values = Vec::new();
        teacher.net.visit_params("", &mut |_, p| values.extend_from_slice(&p.value));
        (values, losses)
    }

    #[test]
    fn chunked_teachers_do_not_depend_on_the_threads() {
        // 40 rows in 3 chunks (14, 13 and 13 rows).
        let one = chunked_run(3, 1, 25);
        for threads in [0, 2, 3] {
            assert!(one == chunked_run(3, threads, 25), "{threads} threads");
        }
        assert!(chunked_run(1, 1, 25) == chunked_run(1, 2, 25));
        // The chunks' loss is the batch's, up to the order of the sums.
        let (whole, chunked) = (chunked_run(1, 1, 1).1, chunked_run(4, 2, 1).1);
        assert!((whole[0] - chunked[0]).abs() <= 1e-6 * whole[0], "{whole:?} vs {chunked:?}");
        assert!(TrainConfig { chunks: 0, ..Default::default() }.validate().is_err());
    }

    #[test]
    fn teachers_fork_into_copies_with_the_same_scores() {
        use crate::{Beso, BesoConfig, DiffusionTeacher, NetConfig, TeacherTrainer};
        use vdd_core::{ClampedDenoiser, ScoreModel, Trainer};
        let states = Mat::from_fn(16, 1, |i, _| (i % 3) as f32);
        let actions = Mat::from_fn(16, 2, |i, j| ((i + j) % 5) as f32 / 2.0 - 1.0);
        let net = NetConfig { hidden_dim: 8, num_blocks: 1, ..Default::default() };
        let config = BesoConfig { net, ..Default::default() };
        let train = TrainConfig { steps: 3, batch_size: 8, ..Default::default() };
        let (s, a) = (states.as_ref(), actions.as_ref());
        let mut trainer = TeacherTrainer::new(&config, &train, s, a, 0).unwrap();
        trainer.run(|_| {}).unwrap();
        let beso: Beso = trainer.finish().unwrap();
        let teacher = DiffusionTeacher::from(beso);
        let mut clamped = ClampedDenoiser::around_data(teacher, a, 0.1).unwrap();
        let mut fork = clamped.fork().expect("learned teachers fork");
        let levels: Vec<f32> = (0..16).map(|i| 0.05 + 0.1 * i as f32).collect();
        let (mut ours, mut theirs) = (Mat::zeros(16, 2), Mat::zeros(16, 2));
        clamped.score(a, s, &levels, ours.as_mut()).unwrap();
        fork.score(a, s, &levels, theirs.as_mut()).unwrap();
        assert!(ours == theirs);
    }
}
