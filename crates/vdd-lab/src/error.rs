//! The experiment layer's error: every crate's error it wires, kept as the source, and the
//! layer's own messages (a recipe that names an unknown method, a method without its teacher).

/// An error of the experiment layer.
#[derive(Debug, thiserror::Error)]
pub enum LabError {
    /// A message of the layer itself (bad recipe content, an unknown name, a missing stage).
    #[error("{0}")]
    Msg(String),
    /// An error with what was being done when it happened.
    #[error("{context}: {source}")]
    Context {
        /// What was being done (`vdd-beso s0`, `student`).
        context: String,
        /// The error.
        #[source]
        source: Box<LabError>,
    },
    /// The core vocabulary (a `Policy` or `ScoreModel`, an implementor's error).
    #[error(transparent)]
    Core(#[from] vdd_core::CoreError),
    /// Layers, optimisers, checkpoints and model files.
    #[error(transparent)]
    Nn(#[from] vdd_nn::NnError),
    /// Datasets, windows, feature maps.
    #[error(transparent)]
    Data(#[from] vdd_data::DataError),
    /// The in-house diffusion teachers and their cache.
    #[error(transparent)]
    Diffusion(#[from] vdd_diffusion::DiffusionError),
    /// The mixture-of-experts student and its cache.
    #[error(transparent)]
    Moe(#[from] vdd_moe::MoeError),
    /// The VDD trainer.
    #[error(transparent)]
    Vdd(#[from] vdd::VddError),
    /// EM and IMC.
    #[error(transparent)]
    Mixture(#[from] vdd_mixture::MixtureError),
    /// CD and CTM.
    #[error(transparent)]
    Consistency(#[from] vdd_consistency::ConsistencyError),
    /// Tasks, rollouts and evaluation.
    #[error(transparent)]
    Task(#[from] vdd_tasks::TaskError),
    /// Teachers imported from PyTorch.
    #[error(transparent)]
    Import(#[from] vdd_import::ImportError),
    /// Metrics, tables and figures.
    #[error(transparent)]
    Report(#[from] vdd_report::Error),
    /// Recipes: resolution, unknown keys, seeds.
    #[error(transparent)]
    Recipe(#[from] vdd_recipe::RecipeError),
    /// The tuning protocol and the tuning log.
    #[error(transparent)]
    Tuning(#[from] crate::tuning::TuningError),
    /// The learned teachers' cache.
    #[error(transparent)]
    TeacherCache(#[from] vdd_diffusion::cache::CacheError),
    /// The distilled students' cache.
    #[error(transparent)]
    StudentCache(#[from] vdd_moe::cache::StudentCacheError),
    /// The Avoiding demonstrations and their dataset.
    #[error(transparent)]
    Dataset(#[from] vdd_tasks::avoiding::dataset::DatasetError),
    /// Reading or writing a file of the run.
    #[error(transparent)]
    Io(#[from] std::io::Error),
    /// JSON of `metrics.json`, curves and cache keys.
    #[error(transparent)]
    Json(#[from] serde_json::Error),
}

impl LabError {
    /// `self` with what was being done when it happened.
    pub fn context(self, context: impl Into<String>) -> Self {
        LabError::Context { context: context.into(), source: Box::new(self) }
    }
}

impl From<String> for LabError {
    fn from(m: String) -> Self {
        LabError::Msg(m)
    }
}

impl From<&str> for LabError {
    fn from(m: &str) -> Self {
        LabError::Msg(m.to_owned())
    }
}

/// The experiment layer's result.
pub type Result<T = (), E = LabError> = std::result::Result<T, E>;
