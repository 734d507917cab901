//! What a user chooses about an imported U-Net teacher rather than its package: the sampler it
//! acts with ([`Sampler`]) and where its observation features come from in the user's raw
//! observation ([`ObsMap`]).

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Serialize};

use crate::diffusers::{SamplerKind, SchedulerConfig};
use crate::error::ImportError;
use crate::normalize::FeatureNormSpec;

/// The sampler an imported U-Net teacher acts with, chosen at run time
/// ([`crate::UnetTeacher::set_sampler`]); the noise process (schedule, prediction type,
/// clipping) stays the package's. The score the teacher gives as a `ScoreModel` does not
/// depend on it.
///
/// ```
/// use vdd_import::Sampler;
/// assert_eq!("ddim:10".parse::<Sampler>()?, Sampler::Ddim { steps: 10 });
/// assert_eq!("ddpm".parse::<Sampler>()?, Sampler::Ddpm { steps: None });
/// assert_eq!(Sampler::Ddpm { steps: Some(20) }.to_string(), "ddpm:20");
/// assert!("ddim".parse::<Sampler>().is_err()); // DDIM needs its step count
/// # Ok::<(), vdd_import::ImportError>(())
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Sampler {
    /// diffusers' `DDPMScheduler` (ancestral, `fixed_small` variance) over `steps` inference
    /// steps; `None` is every trained step (`num_train_timesteps`), as LeRobot trains it.
    Ddpm {
        /// Inference steps (`None`: all `num_train_timesteps`).
        steps: Option<usize>,
    },
    /// diffusers' `DDIMScheduler` (`eta = 0`) over `steps` inference steps ("leading"
    /// spacing).
    Ddim {
        /// Inference steps.
        steps: usize,
    },
}

impl Sampler {
    /// The scheduler configuration `base` with this sampler (checked: `1 ≤ steps ≤ N`).
    pub fn apply(self, base: &SchedulerConfig) -> Result<SchedulerConfig, ImportError> {
        let n = base.num_train_timesteps;
        let (sampler, steps) = match self {
            Self::Ddpm { steps } => (SamplerKind::Ddpm, steps.unwrap_or(n)),
            Self::Ddim { steps } => (SamplerKind::Ddim, steps),
        };
        if steps == 0 || steps > n {
            return Err(ImportError::bad(
                "sampler",
                self.to_string(),
                format!("{steps} steps (1 to num_train_timesteps = {n})"),
            ));
        }
        Ok(SchedulerConfig { sampler, num_inference_steps: steps, ..base.clone() })
    }

    /// The sampler a scheduler configuration runs.
    pub fn of(config: &SchedulerConfig) -> Self {
        match config.sampler {
            SamplerKind::Ddpm if config.num_inference_steps == config.num_train_timesteps => {
                Self::Ddpm { steps: None }
            }
            SamplerKind::Ddpm => Self::Ddpm { steps: Some(config.num_inference_steps) },
            SamplerKind::Ddim => Self::Ddim { steps: config.num_inference_steps },
        }
    }
}

impl fmt::Display for Sampler {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Ddpm { steps: None } => write!(f, "ddpm"),
            Self::Ddpm { steps: Some(s) } => write!(f, "ddpm:{s}"),
            Self::Ddim { steps } => write!(f, "ddim:{steps}"),
        }
    }
}

/// Parses `ddpm` (every trained step), `ddpm:N` or `ddim:N`.
impl FromStr for Sampler {
    type Err = ImportError;

    fn from_str(s: &str) -> Result<Self, ImportError> {
        let bad = || ImportError::bad("sampler", s, "expected ddpm, ddpm:N or ddim:N");
        let (kind, steps) = match s.split_once(':') {
            Some((k, n)) => (k, Some(n.trim().parse::<usize>().map_err(|_| bad())?)),
            None => (s, None),
        };
        match (kind.trim().to_ascii_lowercase().as_str(), steps) {
            ("ddpm", steps) => Ok(Self::Ddpm { steps }),
            ("ddim", Some(steps)) => Ok(Self::Ddim { steps }),
            _ => Err(bad()),
        }
    }
}

/// Where each of a policy's observation features (LeRobot's `observation.state`,
/// `observation.environment_state`) comes from in the user's raw per-step observation: for
/// every feature key, the raw indices of its values in the feature's order.
///
/// The package only knows its features; which entries of an environment's observation they
/// are is the user's knowledge. Stated at import ([`crate::import_lerobot_with`]), checked
/// against the features' shapes, stored in the teacher file (`UnetTeacherSpec::obs_map`) and
/// applied whenever the teacher acts on a raw observation. A raw index may feed more than one
/// feature, not the same feature twice.
///
/// ```
/// use vdd_import::ObsMap;
/// // A 4-wide raw observation whose last two entries are the state, the first two the env.
/// let map: ObsMap = "observation.state=2,3;observation.environment_state=0..2".parse()?;
/// assert_eq!(map.raw_dim(), 4);
/// let mut out = Vec::new();
/// map.gather(&[10.0, 11.0, 12.0, 13.0], &mut out);
/// assert_eq!(out, [12.0, 13.0, 10.0, 11.0]);
/// assert_eq!(map.to_string(), "observation.state=2,3;observation.environment_state=0,1");
/// # Ok::<(), vdd_import::ImportError>(())
/// ```
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ObsMap {
    /// Width of the raw per-step observation.
    raw_dim: usize,
    /// Per feature key, the raw indices of its values.
    features: Vec<(String, Vec<usize>)>,
}

/// Raw observations wider than this are refused (a typo, not an observation).
const MAX_RAW_DIM: usize = 1 << 20;

impl ObsMap {
    /// A map of `raw_dim`-wide raw observations: `features` lists each feature key with the
    /// raw indices of its values. Errors (naming the key) for an index `≥ raw_dim`, an index
    /// repeated within a key, an empty or repeated key.
    pub fn new(raw_dim: usize, features: Vec<(String, Vec<usize>)>) -> Result<Self, ImportError> {
        let map = Self { raw_dim, features };
        map.check()?;
        Ok(map)
    }

    /// Width of the raw per-step observation.
    pub fn raw_dim(&self) -> usize {
        self.raw_dim
    }

    /// Per feature key, the raw indices of its values, in the map's order.
    pub fn features(&self) -> &[(String, Vec<usize>)] {
        &self.features
    }

    /// The raw indices of `key`.
    pub fn indices(&self, key: &str) -> Option<&[usize]> {
        self.features.iter().find(|(k, _)| k == key).map(|(_, v)| v.as_slice())
    }

    fn check(&self) -> Result<(), ImportError> {
        let bad = |key: &str, v: String| Err(ImportError::bad("observation map", key, v));
        if self.raw_dim == 0 || self.raw_dim > MAX_RAW_DIM {
            return bad("raw observation width", self.raw_dim.to_string());
        }
        if self.features.is_empty() {
            return bad("features", "none".into());
        }
        for (i, (key, idx)) in self.features.iter().enumerate() {
            if key.is_empty() || self.features[..i].iter().any(|(k, _)| k == key) {
                return bad(key, "an empty or repeated key".into());
            }
            if idx.is_empty() {
                return bad(key, "no indices".into());
            }
            if let Some(&j) = idx.iter().find(|&&j| j >= self.raw_dim) {
                return bad(
                    key,
                    format!("index {j} out of range for a {}-wide raw observation", self.raw_dim),
                );
            }
            if let Some((p, &j)) = idx.iter().enumerate().find(|(p, j)| idx[..*p].contains(j)) {
                return bad(key, format!("index {j} repeated (position {p})"));
            }
        }
        Ok(())
    }

    /// Checks the map against a policy's features (`features`, in the policy's order): every
    /// feature mapped with as many indices as its width, no other key. `file` names the
    /// teacher in errors.
    pub fn check_features(
        &self,
        features: &[FeatureNormSpec],
        file: &str,
    ) -> Result<(), ImportError> {
        self.check().map_err(|e| ImportError::bad(file, "obs_map", e))?;
        let bad = |key: &str, v: String| {
            Err(ImportError::bad(file, format!("obs_map.{key}"), format!("{self}: {v}")))
        };
        for f in features {
            match self.indices(&f.name) {
                None => return bad(&f.name, "the policy's feature is not mapped".into()),
                Some(idx) if idx.len() != f.dim => {
                    return bad(
                        &f.name,
                        format!("{} indices for a feature of shape [{}]", idx.len(), f.dim),
                    );
                }
                Some(_) => {}
            }
        }
        if let Some((k, _)) =
            self.features.iter().find(|(k, _)| !features.iter().any(|f| &f.name == k))
        {
            let names: Vec<&str> = features.iter().map(|f| f.name.as_str()).collect();
            return bad(k, format!("not a feature of the policy ({})", names.join(", ")));
        }
        Ok(())
    }

    /// Puts the map's features in `order` (the policy's feature order).
    pub(crate) fn ordered(&self, order: &[FeatureNormSpec]) -> Self {
        let features = order
            .iter()
            .filter_map(|f| self.indices(&f.name).map(|i| (f.name.clone(), i.to_vec())))
            .collect();
        Self { raw_dim: self.raw_dim, features }
    }

    /// The features of one raw observation (`raw_dim` values), concatenated in the map's
    /// order, into `out` (cleared first).
    pub fn gather(&self, raw: &[f32], out: &mut Vec<f32>) {
        out.clear();
        for (_, idx) in &self.features {
            out.extend(idx.iter().map(|&j| raw.get(j).copied().unwrap_or(f32::NAN)));
        }
    }

    /// Total width of the mapped features.
    pub fn mapped_dim(&self) -> usize {
        self.features.iter().map(|(_, i)| i.len()).sum()
    }
}

/// `key=i,j,...` entries separated by `;`, as [`FromStr`] reads them.
impl fmt::Display for ObsMap {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (n, (key, idx)) in self.features.iter().enumerate() {
            let idx: Vec<String> = idx.iter().map(usize::to_string).collect();
            write!(f, "{}{key}={}", if n > 0 { ";" } else { "" }, idx.join(","))?;
        }
        Ok(())
    }
}

/// Parses `key=INDICES;key=INDICES...` where `INDICES` is a comma-separated list of raw
/// indices and half-open ranges `a..b`; the raw width is one past the largest index, or
/// stated with a leading `raw_dim=N;` entry (so an unused trailing entry still counts).
impl FromStr for ObsMap {
    type Err = ImportError;

    fn from_str(s: &str) -> Result<Self, ImportError> {
        let bad = |key: &str, v: &str| ImportError::bad("observation map", key, v);
        let mut raw_dim = None;
        let mut features = Vec::new();
        for entry in s.split(';').map(str::trim).filter(|e| !e.is_empty()) {
            let (key, list) =
                entry.split_once('=').ok_or_else(|| bad(entry, "expected key=indices"))?;
            let key = key.trim();
            if key == "raw_dim" {
                raw_dim = Some(list.trim().parse().map_err(|_| bad(key, list))?);
                continue;
            }
            let mut idx = Vec::new();
            for item in list.split(',').map(str::trim) {
                match item.split_once("..") {
                    Some((a, b)) => {
                        let a: usize = a.trim().parse().map_err(|_| bad(key, item))?;
                        let b: usize = b.trim().parse().map_err(|_| bad(key, item))?;
                        if b <= a || b - a > MAX_RAW_DIM {
                            return Err(bad(key, item));
                        }
                        idx.extend(a..b);
                    }
                    None => idx.push(item.parse().map_err(|_| bad(key, item))?),
                }
            }
            features.push((key.to_owned(), idx));
        }
        let widest = features.iter().flat_map(|(_, i)| i.iter()).max().map_or(0, |&m| m + 1);
        Self::new(raw_dim.unwrap_or(widest), features)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn maps_that_do_not_fit_are_refused_naming_the_key() {
        let e = "raw_dim=4;observation.state=2,4".parse::<ObsMap>().unwrap_err();
        assert!(e.to_string().contains("observation.state") && e.to_string().contains("index 4"));
        let e = "observation.state=1,1".parse::<ObsMap>().unwrap_err();
        assert!(e.to_string().contains("repeated"), "{e}");
        let e = "observation.state=a".parse::<ObsMap>().unwrap_err();
        assert!(e.to_string().contains("observation.state"), "{e}");
        assert!("observation.state=0;observation.state=1".parse::<ObsMap>().is_err());
        // The same raw entry may feed two features.
        let m: ObsMap =
            "raw_dim=3;observation.state=0,1;observation.environment_state=1".parse().unwrap();
        assert_eq!((m.raw_dim(), m.mapped_dim()), (3, 3));
        assert_eq!(m.to_string().parse::<ObsMap>().unwrap().features(), m.features());
    }

    #[test]
    fn samplers_are_checked_against_the_trained_steps() {
        use crate::diffusers::{BetaSchedule, Prediction};
        let base = SchedulerConfig {
            sampler: SamplerKind::Ddpm,
            num_train_timesteps: 100,
            beta_start: 1e-4,
            beta_end: 0.02,
            beta_schedule: BetaSchedule::SquaredcosCapV2,
            prediction: Prediction::Epsilon,
            clip_sample: true,
            clip_sample_range: 1.0,
            num_inference_steps: 100,
        };
        let c = Sampler::Ddim { steps: 10 }.apply(&base).unwrap();
        assert_eq!((c.sampler, c.num_inference_steps), (SamplerKind::Ddim, 10));
        assert_eq!(Sampler::of(&c), Sampler::Ddim { steps: 10 });
        assert_eq!(
            Sampler::of(&Sampler::Ddpm { steps: None }.apply(&c).unwrap()),
            Sampler::Ddpm { steps: None }
        );
        let e = Sampler::Ddim { steps: 101 }.apply(&base).unwrap_err();
        assert!(e.to_string().contains("ddim:101"), "{e}");
        assert!(Sampler::Ddim { steps: 0 }.apply(&base).is_err());
    }
}
