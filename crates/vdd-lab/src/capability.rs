//! What a task offers and a row of the results needs (a leaf module: the method, teacher
//! and task modules all name it).

/// What a task offers ([`crate::task::Task::offers`]) and a row needs: its method's
/// ([`crate::method::Info::needs`]), its teacher's ([`crate::teachers::TeacherSource::needs`])
/// and its own (a row's `needs`). A row runs on every task that offers all of it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Capability {
    /// Episodes to roll a policy out in, from raw observations (success, task entropy): any
    /// policy can be evaluated.
    Rollouts,
    /// The learned diffusion teachers (`teachers.beso`, `teachers.ddpm`), trained on the
    /// task's demonstrations.
    LearnedTeachers,
    /// The exact mixture the data come from (the toys), as a teacher and a reference.
    ExactMixture,
    /// The training episodes' raw observations and actions, which a teacher imported with
    /// windows, chunks and features of its own cuts itself (`teachers::imported`).
    RawEpisodes,
    /// Curves over training: a policy evaluated at checkpoints of its training, on episodes
    /// held out from the final evaluation ([`crate::method::Job::curves`]), which checkpoint
    /// selection (row `vdd-beso-selected`) chooses among.
    TrainingCurves,
}
