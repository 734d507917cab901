//! [`LearnedTeacher`]: everything the DDPM and BESO teachers share — data normalisers, the
//! denoiser network with its EMA weights, training, the [`ScoreModel`] and [`Policy`]
//! implementations, save and load. What differs (the diffusion process, its network
//! parameterisation, schedule and samplers) is a [`Process`]: [`crate::Ddpm`] is
//! `LearnedTeacher<DdpmProcess>`, [`crate::Beso`] is `LearnedTeacher<BesoProcess>`.

use std::fmt::Debug;
use std::path::Path;

use faer::reborrow::Reborrow;
use faer::{MatMut, MatRef};
use rand::RngCore;
use serde::Serialize;
use serde::de::DeserializeOwned;
use vdd_core::{
    Affine, CoreError, NoiseProcess, Policy, ScoreModel, Seeds, Trainer, check_act_args, check_len,
    check_score_args, check_shape,
};

use crate::common::{self, PolicyIo, SavedShape, check_batch};
use crate::error::{DiffusionError, Result};
use crate::net::{DenoiserNet, NetConfig};
use crate::normalize::NormalizerKind;
use crate::sampling::SamplerBuffers;
use crate::train::{self, DsmNoise, TrainConfig, TrainProgress};
use vdd_data::DeploySpec;

/// The metadata key of a saved teacher's deployment spec (absent: the identity).
const DEPLOY_SPEC_KEY: &str = "deploy_spec";

/// The part of a learned teacher that depends on the diffusion: its configuration, noise
/// schedule, network parameterisation, training noise and samplers.
///
/// Sealed: implemented by the DDPM (VP, `ε`-prediction) and BESO (VE, EDM denoiser)
/// processes of this crate only.
pub trait Process: DsmNoise + NoiseProcess + Clone + Debug + Send + Sized + 'static {
    /// The teacher's configuration (saved with the weights).
    type Config: Clone + Debug + PartialEq + Serialize + DeserializeOwned;
    /// The samplers it offers.
    type Sampler: Copy + Debug;
    /// The checkpoint's kind tag.
    const KIND: &'static str;
    /// Name of the policy's random stream.
    const POLICY_STREAM: &'static str;
    /// Checks a configuration.
    fn validate(config: &Self::Config) -> Result<()>;
    /// The denoiser network's architecture.
    fn net_config(config: &Self::Config) -> &NetConfig;
    /// How to fit the `(state, action)` normalisers to training data.
    fn normalizer_kinds(config: &Self::Config) -> (NormalizerKind, NormalizerKind);
    /// Builds the process (schedule, sampling grid) from a valid configuration.
    fn build(config: Self::Config) -> Result<Self>;
    /// The configuration, with the current sampler and steps.
    fn config(&self) -> &Self::Config;
    /// The sampler and steps used by `act` and `sample_actions`.
    fn sampler(&self) -> (Self::Sampler, usize);
    /// Selects the sampler and steps.
    fn set_sampler(&mut self, sampler: Self::Sampler, steps: usize) -> Result<()>;
    /// Checks score-query noise levels (`allow_zero`: a level of 0 is a valid target).
    fn check_levels(&self, levels: &[f32], allow_zero: bool) -> Result<(), CoreError>;
    /// The network's prediction at per-row `levels` (`D(x; σ, s)` or `ε̂(x, t, s)`), without
    /// argument checks.
    fn evaluate(
        &mut self,
        net: &mut DenoiserNet,
        x: MatRef<'_, f32>,
        levels: &[f32],
        states: MatRef<'_, f32>,
        out: MatMut<'_, f32>,
    );
    /// Turns [`Process::evaluate`]'s output at `x` into the score, in place.
    fn prediction_to_score(&self, x: MatRef<'_, f32>, levels: &[f32], out: MatMut<'_, f32>);
    /// Samples one action per row of (normalised, checked) `states` into `out`, with the
    /// configured sampler (`how = None`) or the given one.
    #[allow(clippy::too_many_arguments)]
    fn sample(
        &mut self,
        net: &mut DenoiserNet,
        buf: &mut SamplerBuffers,
        how: Option<(Self::Sampler, usize)>,
        states: MatRef<'_, f32>,
        rng: &mut dyn RngCore,
        out: MatMut<'_, f32>,
    ) -> Result<(), CoreError>;
}

/// A learned diffusion teacher: a [`DenoiserNet`] trained by denoising score matching on
/// normalised data, with the diffusion process `P` (DDPM or BESO).
///
/// Use it through its aliases [`crate::Ddpm`] and [`crate::Beso`], or [`crate::DiffusionTeacher`]
/// for either. The [`ScoreModel`] works in the **normalised** space ([`LearnedTeacher::normalizers`]);
/// the [`Policy`] maps raw observations to raw actions. Sampling and scores use the
/// exponential-moving-average weights.
#[derive(Debug, Clone)]
pub struct LearnedTeacher<P: Process> {
    pub(crate) process: P,
    train_config: Option<TrainConfig>,
    state_norm: Affine,
    action_norm: Affine,
    pub(crate) net: DenoiserNet,
    pub(crate) sampler_buf: SamplerBuffers,
    io: PolicyIo,
    rng: vdd_core::Rng,
    deploy_spec: DeploySpec,
}

impl<P: Process> LearnedTeacher<P> {
    /// An untrained teacher with freshly initialised weights and the given normalisers
    /// (their dimensions give the state and action dimensions).
    pub fn new(
        config: &P::Config,
        state_norm: Affine,
        action_norm: Affine,
        seed: u64,
    ) -> Result<Self> {
        P::validate(config)?;
        let net = DenoiserNet::new(
            P::net_config(config),
            action_norm.dim(),
            state_norm.dim(),
            &mut Seeds::new(seed).stream("init"),
        )?;
        Self::from_parts(config.clone(), None, state_norm, action_norm, net, seed)
    }

    fn from_parts(
        config: P::Config,
        train_config: Option<TrainConfig>,
        state_norm: Affine,
        action_norm: Affine,
        net: DenoiserNet,
        seed: u64,
    ) -> Result<Self> {
        Ok(Self {
            process: P::build(config)?,
            train_config,
            state_norm,
            action_norm,
            net,
            sampler_buf: SamplerBuffers::default(),
            io: PolicyIo::default(),
            rng: Seeds::new(seed).stream(P::POLICY_STREAM),
            deploy_spec: DeploySpec::identity(),
        })
    }

    /// How the teacher acts on raw observations (features, observation window, action chunk):
    /// saved with it; the identity (one featureless observation per action) unless set.
    pub fn deploy_spec(&self) -> &DeploySpec {
        &self.deploy_spec
    }

    /// Sets [`LearnedTeacher::deploy_spec`], checked against the teacher's state and action
    /// dimensions (a window must divide the state, a chunk the action).
    pub fn set_deploy_spec(&mut self, spec: DeploySpec) -> Result<()> {
        spec.check_policy_dims(self.state_dim(), self.action_dim())?;
        self.deploy_spec = spec;
        Ok(())
    }

    /// Trains a teacher on raw `states` (`n x d_s`) and `actions` (`n x d_a`, action chunks
    /// flattened) by seeded minibatch denoising score matching with Adam; the returned teacher
    /// samples with the EMA weights. `progress` receives a report every `train.log_every`
    /// steps (nothing is printed).
    ///
    /// This is [`TeacherTrainer`] run to the end; use the trainer to step training yourself.
    pub fn train(
        config: &P::Config,
        train: &TrainConfig,
        states: MatRef<'_, f32>,
        actions: MatRef<'_, f32>,
        seed: u64,
        progress: &mut dyn FnMut(TrainProgress),
    ) -> Result<Self> {
        let mut trainer = TeacherTrainer::new(config, train, states, actions, seed)?;
        trainer.run(|report| {
            if let Some(p) = report {
                progress(*p);
            }
        })?;
        trainer.finish()
    }

    /// Dimension of one (flattened) action; the same for the score model and the policy.
    pub fn action_dim(&self) -> usize {
        self.action_norm.dim()
    }

    /// Dimension of one state / observation.
    pub fn state_dim(&self) -> usize {
        self.state_norm.dim()
    }

    /// The configuration (including the current sampler and steps).
    pub fn config(&self) -> &P::Config {
        self.process.config()
    }

    /// The training configuration, when the teacher was trained (or loaded from a trained one).
    pub fn train_config(&self) -> Option<&TrainConfig> {
        self.train_config.as_ref()
    }

    /// The `(state, action)` normalisers; the [`ScoreModel`] works in their normalised space.
    pub fn normalizers(&self) -> (&Affine, &Affine) {
        (&self.state_norm, &self.action_norm)
    }

    /// The network (EMA weights).
    pub fn net(&self) -> &DenoiserNet {
        &self.net
    }

    /// Selects the sampler and number of steps used by `act` and `sample_actions`.
    pub fn set_sampler(&mut self, sampler: P::Sampler, steps: usize) -> Result<()> {
        self.process.set_sampler(sampler, steps)
    }

    /// The sampler and number of steps used by `act` and `sample_actions`.
    pub fn sampler(&self) -> (P::Sampler, usize) {
        self.process.sampler()
    }

    /// Checks a batched network query: `x` (`n x d_a`) and `states` (`n x d_s`) finite, one
    /// valid level per row, `out` `n x d_a`.
    pub(crate) fn check_query(
        &self,
        x: MatRef<'_, f32>,
        levels: &[f32],
        states: MatRef<'_, f32>,
        out: MatRef<'_, f32>,
        allow_zero: bool,
    ) -> Result<(), CoreError> {
        let n = x.nrows();
        check_batch("x", x, n, self.action_dim())?;
        check_batch("states", states, n, self.state_dim())?;
        check_len("noise levels", levels.len(), n)?;
        check_shape("output", out, n, self.action_dim())?;
        self.process.check_levels(levels, allow_zero)
    }

    /// The network's prediction after argument checks.
    pub(crate) fn evaluate_checked(
        &mut self,
        x: MatRef<'_, f32>,
        levels: &[f32],
        states: MatRef<'_, f32>,
        out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        self.check_query(x, levels, states, out.rb(), false)?;
        self.process.evaluate(&mut self.net, x, levels, states, out);
        Ok(())
    }

    /// Samples one action per row of normalised `states` into `out` with an explicit sampler
    /// and number of steps (normalised space).
    pub fn sample_with(
        &mut self,
        sampler: P::Sampler,
        steps: usize,
        states: MatRef<'_, f32>,
        rng: &mut dyn RngCore,
        out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        self.sample_checked(Some((sampler, steps)), states, rng, out)
    }

    fn sample_checked(
        &mut self,
        how: Option<(P::Sampler, usize)>,
        states: MatRef<'_, f32>,
        rng: &mut dyn RngCore,
        out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        let n = states.nrows();
        check_batch("states", states, n, self.state_dim())?;
        check_shape("sampled actions", out.rb(), n, self.action_dim())?;
        self.process.sample(&mut self.net, &mut self.sampler_buf, how, states, rng, out)
    }

    /// Saves the EMA weights (`safetensors`) with the config, dimensions, normalisers and the
    /// training config as JSON metadata; the write is atomic.
    ///
    /// What is written can be loaded: weights beyond the loader's bound or normalisers outside
    /// theirs ([`vdd_core::Affine::new`]) are an error naming the value, and nothing is written.
    pub fn save(&self, path: &Path) -> Result<()> {
        for n in [&self.state_norm, &self.action_norm] {
            n.validate().map_err(|e| crate::DiffusionError::BadMetadata {
                path: path.to_owned(),
                key: common::SHAPE_KEY,
                source: Box::new(e),
            })?;
        }
        let shape = SavedShape {
            state_dim: self.state_dim(),
            action_dim: self.action_dim(),
            state_normalizer: self.state_norm.clone(),
            action_normalizer: self.action_norm.clone(),
        };
        let mut meta =
            common::metadata(P::KIND, self.config(), &shape, self.train_config.as_ref())?;
        if self.deploy_spec != DeploySpec::identity() {
            let spec = serde_json::to_string(&self.deploy_spec).map_err(|source| {
                DiffusionError::SerializeMetadata { key: DEPLOY_SPEC_KEY, source }
            })?;
            meta.insert(DEPLOY_SPEC_KEY.to_owned(), spec);
        }
        vdd_nn::io::save_safetensors(path, &self.net, &meta)?;
        Ok(())
    }

    /// Loads a teacher of this kind saved by [`LearnedTeacher::save`]; its policy stream is
    /// seeded with `seed`.
    pub fn load(path: &Path, seed: u64) -> Result<Self> {
        let (meta, elements) = vdd_nn::io::read_header(path)?;
        let (config, shape, train): (P::Config, SavedShape, Option<TrainConfig>) =
            common::parse_metadata(path, &meta, P::KIND)?;
        P::validate(&config).map_err(|e| common::format_err(path, e))?;
        let max = vdd_nn::limits::MAX_WIDTH;
        if shape.action_dim > max || shape.state_dim > max {
            return Err(common::format_err(
                path,
                format!(
                    "`shape` metadata: action_dim {} and state_dim {} must be <= {max}",
                    shape.action_dim, shape.state_dim
                ),
            ));
        }
        let mlp = P::net_config(&config).mlp_config(shape.action_dim, shape.state_dim, 1);
        vdd_nn::io::check_fits(path, "the `config` metadata", mlp.num_params(), elements)?;
        let mut net = DenoiserNet::new(
            P::net_config(&config),
            shape.action_dim,
            shape.state_dim,
            &mut Seeds::new(0).stream("init"),
        )?;
        vdd_nn::io::load_safetensors(path, &mut net)?;
        let (sn, an) = (shape.state_normalizer, shape.action_normalizer);
        let mut teacher = Self::from_parts(config, train, sn, an, net, seed)?;
        if let Some(json) = meta.get(DEPLOY_SPEC_KEY) {
            let bad = |e: Box<dyn std::error::Error + Send + Sync>| DiffusionError::BadMetadata {
                path: path.to_owned(),
                key: DEPLOY_SPEC_KEY,
                source: e,
            };
            let spec: DeploySpec = serde_json::from_str(json).map_err(|e| bad(Box::new(e)))?;
            spec.validate().map_err(|e| bad(Box::new(e)))?;
            teacher.set_deploy_spec(spec).map_err(|e| bad(Box::new(e)))?;
        }
        Ok(teacher)
    }

    pub(crate) fn kind() -> &'static str {
        P::KIND
    }

    /// The DSM loss of the teacher's process on a batch, with noise drawn from `seed`
    /// (gradient checks).
    #[cfg(test)]
    pub(crate) fn objective_for_tests(
        &self,
    ) -> impl FnMut(&mut DenoiserNet, MatRef<'_, f32>, MatRef<'_, f32>, u64, bool) -> f32 + use<P>
    {
        let process = self.process.clone();
        let mut dsm = train::Dsm::default();
        move |net, a, s, seed, backward| {
            dsm.draw(&process, a.nrows(), a.ncols(), &mut Seeds::new(seed).stream("t"));
            dsm.loss(net, a, s, backward)
        }
    }
}

/// Denoising-score-matching training of a [`LearnedTeacher`] as a [`Trainer`]: one seeded
/// minibatch Adam step per [`Trainer::step`], which reports a [`TrainProgress`] every
/// `train.log_every` steps and after the last (`None` otherwise); [`Trainer::finish`] returns
/// the teacher with the EMA weights. One seed determines the run: the network's
/// initialisation (`"init"`), the minibatches (`"minibatch"`) and the training noise
/// (`"dsm-noise"`) are its streams.
///
/// ```
/// use faer::Mat;
/// use vdd_core::Trainer;
/// use vdd_diffusion::{Beso, BesoConfig, NetConfig, TeacherTrainer, TrainConfig};
///
/// let states = Mat::<f32>::zeros(64, 1);
/// let actions = Mat::from_fn(64, 2, |i, _| if i % 2 == 0 { 1.0 } else { -1.0 });
/// let config = BesoConfig { net: NetConfig { hidden_dim: 16, ..Default::default() }, ..Default::default() };
/// let train = TrainConfig { steps: 20, log_every: 10, ..Default::default() };
/// let mut trainer = TeacherTrainer::new(&config, &train, states.as_ref(), actions.as_ref(), 0)?;
/// let mut reports = Vec::new();
/// trainer.run(|r| reports.extend(*r))?;
/// assert_eq!(reports.iter().map(|p| p.step).collect::<Vec<_>>(), [10, 20]);
/// let teacher: Beso = trainer.finish()?;
/// # Ok::<(), vdd_diffusion::DiffusionError>(())
/// ```
pub struct TeacherTrainer<P: Process> {
    config: P::Config,
    train: TrainConfig,
    seed: u64,
    process: P,
    run: train::DsmLoop,
}

impl<P: Process> TeacherTrainer<P> {
    /// Prepares training on raw `states` (`n x d_s`) and `actions` (`n x d_a`): validates the
    /// configurations and data, fits the normalisers and initialises the network from `seed`.
    pub fn new(
        config: &P::Config,
        train: &TrainConfig,
        states: MatRef<'_, f32>,
        actions: MatRef<'_, f32>,
        seed: u64,
    ) -> Result<Self> {
        P::validate(config)?;
        train.validate()?;
        let (state_kind, action_kind) = P::normalizer_kinds(config);
        let data = train::prepare_data(states, actions, state_kind, action_kind)?;
        let seeds = Seeds::new(seed);
        let net = DenoiserNet::new(
            P::net_config(config),
            actions.ncols(),
            states.ncols(),
            &mut seeds.stream("init"),
        )?;
        let process = P::build(config.clone())?;
        let run = train::DsmLoop::new(net, train, data, &seeds)?;
        Ok(Self { config: config.clone(), train: train.clone(), seed, process, run })
    }

    /// Runs the chunks of each step ([`TrainConfig::chunks`]) on `threads` threads: 1 in the
    /// calling thread, more on a pool of that many threads of its own, 0 (the default) on the
    /// process-wide pool (`RAYON_NUM_THREADS` threads, default one per core), shared with the
    /// other trainings of the process. The trained teacher is the same whatever the count.
    pub fn set_threads(&mut self, threads: usize) -> Result<()> {
        self.run.set_threads(threads)
    }
}

impl<P: Process> Trainer for TeacherTrainer<P> {
    type Report = Option<TrainProgress>;
    type Output = LearnedTeacher<P>;
    type Error = DiffusionError;

    fn step(&mut self) -> Result<Option<TrainProgress>> {
        self.run.step(&self.process)
    }

    fn iteration(&self) -> usize {
        self.run.steps_done() as usize
    }

    fn iterations(&self) -> usize {
        self.train.steps as usize
    }

    /// The teacher with the EMA weights, its normalisers and its training configuration.
    fn finish(self) -> Result<LearnedTeacher<P>> {
        let (ema, data) = self.run.finish();
        LearnedTeacher::from_parts(
            self.config,
            Some(self.train),
            data.state_norm,
            data.action_norm,
            ema,
            self.seed,
        )
    }
}

impl<P: Process> ScoreModel for LearnedTeacher<P> {
    fn action_dim(&self) -> usize {
        self.action_norm.dim()
    }

    fn state_dim(&self) -> usize {
        self.state_norm.dim()
    }

    /// The process's: BESO's levels are `σ ∈ [σ_min, σ_max]`, clamped when drawn; DDPM's are
    /// the time `t ∈ [MIN_TIME, N]` (or `[1, N]`, rounded onto the grid, with discrete
    /// training times), its denoiser form `x̂₀ = (a + (1 − ᾱ(t)) s)/√ᾱ(t)`.
    fn noise_process(&self) -> Option<&dyn NoiseProcess> {
        Some(&self.process)
    }

    /// The score in the normalised space: `(D(a; σ, s) − a)/σ²` (BESO) or
    /// `−ε̂(a, t, s)/sqrt(1 − ᾱ(t))` (DDPM).
    fn score(
        &mut self,
        actions: MatRef<'_, f32>,
        states: MatRef<'_, f32>,
        noise_levels: &[f32],
        mut out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        check_score_args(self, actions, states, noise_levels, out.rb())?;
        self.evaluate_checked(actions, noise_levels, states, out.as_mut())?;
        self.process.prediction_to_score(actions, noise_levels, out.as_mut());
        vdd_core::check_finite("scores", out.rb())
    }

    /// Samples with the configured sampler and steps (normalised space).
    fn sample_actions(
        &mut self,
        states: MatRef<'_, f32>,
        rng: &mut dyn RngCore,
        mut out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        self.sample_checked(None, states, rng, out.as_mut())?;
        vdd_core::check_finite("sampled actions", out.rb())
    }

    /// A copy of the teacher (its network, normalisers and buffers).
    fn fork(&self) -> Option<Box<dyn ScoreModel + Send>> {
        Some(Box::new(self.clone()))
    }
}

impl<P: Process> Policy for LearnedTeacher<P> {
    fn obs_dim(&self) -> usize {
        self.state_norm.dim()
    }

    fn action_dim(&self) -> usize {
        self.action_norm.dim()
    }

    fn seed(&mut self, seed: u64) {
        self.rng = Seeds::new(seed).stream(P::POLICY_STREAM);
    }

    fn act_into(&mut self, obs: &[f32], action: &mut [f32]) -> Result<(), CoreError> {
        check_act_args(self, obs, action)?;
        let (ds, da) = (self.state_norm.dim(), self.action_norm.dim());
        self.act_batch(
            MatRef::from_row_major_slice(obs, 1, ds),
            MatMut::from_row_major_slice_mut(action, 1, da),
        )
    }

    fn act_batch(
        &mut self,
        obs: MatRef<'_, f32>,
        mut actions: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        let n = obs.nrows();
        let (ds, da) = (self.state_norm.dim(), self.action_norm.dim());
        check_batch("observations", obs, n, ds)?;
        check_shape("actions", actions.rb(), n, da)?;
        self.io.prepare(n, ds, da);
        self.io.load_obs(obs, &self.state_norm);
        let Self { process, net, sampler_buf, io, rng, .. } = self;
        process.sample(net, sampler_buf, None, io.obs.as_ref(), rng, io.act.as_mut())?;
        self.io.store_actions(&self.action_norm, actions.as_mut());
        vdd_core::check_finite("actions", actions.rb())
    }
}
