//! What distilling an imported U-Net teacher needs besides the teacher: the samples it was
//! trained on ([`UnetTeacher::training_windows`]), the space it works in
//! ([`UnetTeacher::teacher_space`], for the trainer's `vdd::TeacherSpace`) and how a student
//! that emits its whole chunk acts ([`UnetTeacher::chunk_deploy_spec`]).

use faer::Mat;
use vdd_core::Affine;
use vdd_data::{DeploySpec, Episodes};

use crate::error::ImportError;
use crate::unet_teacher::UnetTeacher;

impl UnetTeacher {
    /// The samples of `episodes` (raw observations already through the spec's feature map,
    /// `raw_obs_dim` wide; the spec's observation map is applied here) as
    /// LeRobot's dataset builds them for this teacher with `delta_timestamps`: for every step
    /// `t`, the observation window `t − n_obs_steps + 1 ..= t` and the action chunk
    /// `t − n_obs_steps + 1 .. t − n_obs_steps + 1 + horizon`, indices clamped to the episode
    /// (the first and last steps repeat). Rows: the mapped window (`n_obs_steps · obs_dim`,
    /// oldest first) and the raw chunk (`horizon · action_dim`, step-major) — the teacher's
    /// state and action before its normalisers.
    ///
    /// ```
    /// # fn main() -> Result<(), Box<dyn std::error::Error>> {
    /// # let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/fixtures/import/lerobot_unet_ddim");
    /// let teacher = vdd_import::import_lerobot(&dir)?; // window 1, horizon 8, 7-D obs, 2-D actions
    /// let obs = faer::Mat::from_fn(3, 7, |t, _| t as f32);
    /// let act = faer::Mat::from_fn(3, 2, |t, _| 10.0 * t as f32);
    /// let episodes = vdd_data::Episodes::from_episodes(vec![obs], vec![act])?;
    /// let (states, chunks) = teacher.training_windows(&episodes)?;
    /// assert_eq!((states.nrows(), states.ncols(), chunks.ncols()), (3, 7, 16));
    /// assert_eq!((chunks[(1, 0)], chunks[(1, 2)], chunks[(1, 15)]), (10.0, 20.0, 20.0));
    /// # Ok(()) }
    /// ```
    pub fn training_windows(
        &self,
        episodes: &Episodes,
    ) -> Result<(Mat<f32>, Mat<f32>), ImportError> {
        let s = self.spec();
        let (w, h) = (s.n_obs_steps, s.horizon);
        let (d_obs, d_act, d_raw) = (s.obs_dim(), s.unet.input_dim, s.raw_obs_dim());
        if episodes.obs_dim() != d_raw || episodes.act_dim() != d_act {
            return Err(ImportError::bad(
                "episodes",
                "dimensions",
                format!(
                    "observations {} and actions {} for a teacher of {d_raw} and {d_act}",
                    episodes.obs_dim(),
                    episodes.act_dim()
                ),
            ));
        }
        let rows = episodes.num_steps();
        let mut states = Mat::<f32>::zeros(rows, w * d_obs);
        let mut chunks = Mat::<f32>::zeros(rows, h * d_act);
        let mut row = 0;
        let (mut raw, mut mapped) = (vec![0.0f32; d_raw], Vec::with_capacity(d_obs));
        for e in 0..episodes.num_episodes() {
            let (obs, act) = (episodes.observations(e), episodes.actions(e));
            let len = obs.nrows();
            let at = |t: usize, k: usize| (t + k).saturating_sub(w - 1).min(len - 1);
            for t in 0..len {
                for k in 0..w {
                    for (j, v) in raw.iter_mut().enumerate() {
                        *v = obs[(at(t, k), j)];
                    }
                    self.map_obs_window(&raw, &mut mapped);
                    for (j, &v) in mapped.iter().enumerate() {
                        states[(row, k * d_obs + j)] = v;
                    }
                }
                for k in 0..h {
                    for j in 0..d_act {
                        chunks[(row, k * d_act + j)] = act[(at(t, k), j)];
                    }
                }
                row += 1;
            }
        }
        Ok((states, chunks))
    }

    /// The teacher's normalisers as affine maps `(x − offset) / scale` of its whole state
    /// (the observation window: each step's features in order, repeated over the window) and
    /// its whole action (the chunk): the space its [`vdd_core::ScoreModel`] works in, for the
    /// trainer's `vdd::TeacherSpace::normalized` and as the student's own normalisers.
    ///
    /// Errors for a map that is not a positive scaling (a diffusion_policy normaliser with a
    /// negative scale, or a constant feature whose scale is `eps`-small).
    pub fn teacher_space(&self) -> Result<(Affine, Affine), ImportError> {
        let s = self.spec();
        let (mut off, mut scale) = (Vec::new(), Vec::new());
        for n in self.obs_normalizers() {
            let (o, c) = n.as_offset_scale();
            off.extend(o);
            scale.extend(c);
        }
        let states = Affine::new(off.repeat(s.n_obs_steps), scale.repeat(s.n_obs_steps))
            .map_err(|e| ImportError::bad("teacher", "observation normalizer", e))?;
        let (o, c) = self.action_normalizer().as_offset_scale();
        let actions = Affine::new(o.repeat(s.horizon), c.repeat(s.horizon))
            .map_err(|e| ImportError::bad("teacher", "action normalizer", e))?;
        Ok((states, actions))
    }

    /// How a policy that emits the teacher's whole chunk (a distilled student: state the
    /// observation window, action the raw chunk) acts as the teacher's package does: the
    /// spec's feature map, a window of `n_obs_steps`, a chunk of `horizon` steps executed from
    /// index `action_start` for `n_action_steps` steps. The spec's observation map
    /// ([`crate::ObsMap`]) is not part of a `DeploySpec`: a student of a teacher imported
    /// with one is trained on mapped windows ([`UnetTeacher::training_windows`]) and must be
    /// given mapped observations.
    pub fn chunk_deploy_spec(&self) -> DeploySpec {
        let s = self.spec();
        DeploySpec {
            features: s.features.clone(),
            obs_window: s.n_obs_steps,
            action_chunk: s.horizon,
            execute_steps: s.n_action_steps,
            chunk_start: s.action_start,
        }
    }
}
