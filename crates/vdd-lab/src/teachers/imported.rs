//! `imported`: a diffusion policy trained in PyTorch and imported by `cargo xtask import` (a
//! [`vdd_import`] teacher file), named by the recipe key `imported.teacher` (`--teacher FILE`).
//! Nothing is trained: the driver loads the file once per run ([`TeacherSource::load`]), cuts
//! the task's raw training episodes into the teacher's own windows and chunks through its
//! feature map ([`LoadedTeacher::training_data`], the data of its rows), and its rows act
//! through the teacher's own deployment (window, chunk, features:
//! [`LoadedTeacher::deploy_spec`]). Rows: `imported` (the teacher rolled out) and
//! `vdd-imported` (VDD with `vdd.imported`).

use std::path::Path;

use faer::Mat;
use vdd_core::NoiseConvention;
use vdd_data::{DeploySpec, Episodes, TrainingData};
use vdd_diffusion::TeacherKind;
use vdd_import::{ImportedTeacher, UnetTeacher};

use super::TeacherSource;
use crate::capability::Capability;

/// The recipe key of the teacher file.
pub const FILE_KEY: &str = "imported.teacher";

/// The imported-teacher source.
pub struct Imported;

/// `imported`.
pub const IMPORTED: Imported = Imported;

impl TeacherSource for Imported {
    fn name(&self) -> &'static str {
        "imported"
    }
    fn kind(&self) -> Option<TeacherKind> {
        None
    }
    fn needs(&self) -> &'static [Capability] {
        &[Capability::RawEpisodes]
    }
    fn keys(&self) -> &'static [&'static str] {
        &[FILE_KEY]
    }
    /// Diffusers' steps t ∈ [1, N] (the imported U-Nets are VP teachers).
    fn noise_unit(&self) -> NoiseConvention {
        NoiseConvention::Time
    }
    fn loads_file(&self) -> bool {
        true
    }
    fn file(&self, tree: &toml::Table) -> crate::Result<Option<String>> {
        let file: String = crate::recipe::get_path(tree, FILE_KEY)?.unwrap_or_default();
        if file.is_empty() {
            return Err(format!(
                "the rows of the imported teacher need its file: --teacher FILE (`{FILE_KEY}`)"
            )
            .into());
        }
        Ok(Some(file))
    }
    fn load(&self, file: &str) -> crate::Result<LoadedTeacher> {
        LoadedTeacher::load(file)
    }
}

/// A teacher loaded from a file, as the rows of its source use it.
#[derive(Debug, Clone)]
pub struct LoadedTeacher {
    /// The file, as the recipe names it.
    pub file: String,
    /// The teacher.
    pub teacher: UnetTeacher,
    /// A hash of the file's bytes (the keys of students distilled from it).
    pub hash: String,
}

impl LoadedTeacher {
    /// Loads the teacher file `file` (a `cargo xtask import` file).
    pub fn load(file: &str) -> crate::Result<Self> {
        let ImportedTeacher::Unet1d(teacher) = vdd_import::load_teacher(Path::new(file))?;
        // The loader has read it within its bound; the hash reads it again within the same.
        let bytes = vdd_nn::io::read_bounded(Path::new(file), vdd_nn::io::MAX_FILE_BYTES)?;
        let hash = format!("{:016x}", vdd_core::hash::fnv1a(&bytes));
        Ok(Self { file: file.to_owned(), teacher: *teacher, hash })
    }

    /// The observation map the teacher was imported with, if any: it acts on the mapped
    /// observation, which a student's deployment cannot carry yet.
    pub fn obs_map(&self) -> Option<String> {
        self.teacher.spec().obs_map.as_ref().map(|m| m.to_string())
    }

    /// The source name its file states (`lerobot`, `diffusion_policy`): its rows are labelled
    /// with it (`imported` → `lerobot`, `vdd-imported` → `vdd-lerobot`). A name that is not
    /// lower-case letters, digits, `_` and `-` (at most 32), which would not do in a file name,
    /// reads `imported`.
    pub fn source(&self) -> &str {
        let s = self.teacher.spec().source.as_str();
        let plain = |c: char| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '_' || c == '-';
        if !s.is_empty() && s.len() <= 32 && s.chars().all(plain) { s } else { "imported" }
    }

    /// The data of its rows: the raw training episodes (`raw_obs` per episode, with the
    /// episodes' `actions`) through the teacher's feature map, cut into its observation
    /// windows and action chunks, with the teacher's normalisers as the data's (the space
    /// its score works in).
    pub fn training_data(
        &self,
        raw_obs: &[Mat<f32>],
        actions: Vec<Mat<f32>>,
    ) -> crate::Result<TrainingData> {
        let map = self.teacher.spec().features.resolve()?;
        let featured: Result<Vec<_>, _> =
            raw_obs.iter().map(|o| map.apply_rows(o.as_ref())).collect();
        let episodes = Episodes::from_episodes(featured?, actions)?;
        let (states, chunks) = self.teacher.training_windows(&episodes)?;
        let (sn, an) = self.teacher.teacher_space()?;
        Ok(TrainingData {
            states_normalized: sn.normalize_rows(states.as_ref())?,
            actions_normalized: an.normalize_rows(chunks.as_ref())?,
            states,
            actions: chunks,
            state_normalizer: sn,
            action_normalizer: an,
            exact: None,
        })
    }

    /// How the teacher acts on raw observations (its package's window, chunk and features).
    pub fn deploy_spec(&self) -> DeploySpec {
        self.teacher.deploy_spec()
    }

    /// How a student that emits the teacher's whole chunk acts on raw observations.
    pub fn chunk_deploy_spec(&self) -> DeploySpec {
        self.teacher.chunk_deploy_spec()
    }
}
