//! Deployment: the spec a mixture is saved with, and loading a saved mixture as a policy on
//! raw environment observations.

use std::path::Path;

use vdd_core::{Expert, Policy};
use vdd_data::{DeploySpec, Windowed};

use super::Moe;
use crate::error::MoeError;
use crate::experts::ExpertFamily;

/// A mixture acting on raw environment observations: the mixture wrapped by its
/// [`DeploySpec`] (feature map, observation window, action chunk, executed steps). The
/// mixture's own normalisers and act mode apply inside. [`Windowed::inner`] reaches the mixture
/// (e.g. [`Moe::last_experts`]).
pub type DeployedPolicy<E = ExpertFamily> = Windowed<Moe<E>>;

/// Loads a mixture saved by [`Moe::save`] as a policy on raw environment observations: one
/// call, nothing else needed. The file's deployment spec says how raw observations become the
/// mixture's states (feature map, window) and how its predicted chunks become actions; a file
/// saved without a spec (before specs existed) acts on raw observations directly, as the
/// identity spec says. A spec that is invalid or does not fit the mixture is an error naming
/// the setting and its value.
///
/// ```
/// use vdd_core::Policy;
/// use vdd_data::DeploySpec;
/// use vdd_data::features::POSITION_AND_LAG;
/// use vdd_moe::{Moe, MoeConfig};
///
/// // A mixture trained on windows of 2 featured 4-D observations, predicting 3 2-D actions.
/// let mut moe = Moe::from_config(MoeConfig::toy(8, 6, 4), 0)?;
/// let spec = DeploySpec { obs_window: 2, action_chunk: 3, execute_steps: 2, ..DeploySpec::identity() };
/// moe.set_deploy_spec(spec.with_features(POSITION_AND_LAG))?;
/// let dir = std::env::temp_dir().join(format!("vdd-moe-deploy-doc-{}", std::process::id()));
/// std::fs::create_dir_all(&dir)?;
/// let path = dir.join("policy.safetensors");
/// moe.save(&path)?;
///
/// // Deployment: raw 4-D observations in, one 2-D action per step out.
/// let mut policy = vdd_moe::load_policy(&path)?;
/// assert_eq!((policy.obs_dim(), policy.action_dim()), (4, 2));
/// policy.seed(7);
/// let action = policy.act(&[0.1, 0.2, 0.3, 0.4])?;
/// assert_eq!(action.len(), 2);
/// # std::fs::remove_dir_all(&dir)?;
/// # Ok::<(), Box<dyn std::error::Error>>(())
/// ```
pub fn load_policy(path: &Path) -> Result<DeployedPolicy, MoeError> {
    Moe::load(path)?.into_policy()
}

impl<E: Expert> Moe<E> {
    /// How the mixture meets raw observations when deployed ([`DeploySpec::identity`] unless
    /// set): saved with it by [`Moe::save`], applied by [`Moe::into_policy`] and
    /// [`load_policy`].
    pub fn deploy_spec(&self) -> &DeploySpec {
        &self.deploy_spec
    }

    /// Sets the deployment spec: the feature map the training observations went through, the
    /// observation window and action chunk the mixture's states and actions are made of, and
    /// the actions of each chunk to execute. An error (naming the setting and its value) if the
    /// spec is invalid or does not fit the mixture's dimensions; then nothing changes.
    ///
    /// ```
    /// use vdd_data::DeploySpec;
    /// use vdd_moe::{Moe, MoeConfig};
    ///
    /// let mut moe = Moe::from_config(MoeConfig::toy(4, 2, 3), 0)?;
    /// let chunked = DeploySpec { action_chunk: 2, execute_steps: 1, ..DeploySpec::identity() };
    /// moe.set_deploy_spec(chunked.clone())?; // 2-D actions: chunks of two 1-D actions
    /// assert_eq!(moe.deploy_spec(), &chunked);
    /// let err = moe.set_deploy_spec(DeploySpec { obs_window: 3, ..chunked.clone() }).unwrap_err();
    /// assert!(err.to_string().contains("`obs_window` = 3"), "{err}");
    /// assert_eq!(moe.deploy_spec(), &chunked);
    /// # Ok::<(), vdd_moe::MoeError>(())
    /// ```
    pub fn set_deploy_spec(&mut self, spec: DeploySpec) -> Result<(), MoeError> {
        spec.check_policy_dims(self.obs_dim(), self.action_dim())?;
        self.deploy_spec = spec;
        Ok(())
    }

    /// The mixture as a policy on raw observations, by its [`Moe::deploy_spec`]: what
    /// [`load_policy`] returns for the saved mixture.
    ///
    /// ```
    /// use vdd_core::Policy;
    /// use vdd_data::DeploySpec;
    /// use vdd_moe::{Moe, MoeConfig};
    ///
    /// let mut moe = Moe::from_config(MoeConfig::toy(4, 2, 3), 0)?;
    /// moe.set_deploy_spec(DeploySpec { obs_window: 2, ..DeploySpec::identity() })?;
    /// let mut policy = moe.into_policy()?;
    /// assert_eq!(policy.obs_dim(), 2); // raw observations: half of the 2-step window
    /// policy.act(&[0.5, -0.5])?;
    /// assert_eq!(policy.inner().last_experts().len(), 1);
    /// # Ok::<(), vdd_moe::MoeError>(())
    /// ```
    pub fn into_policy(self) -> Result<DeployedPolicy<E>, MoeError> {
        let spec = self.deploy_spec.clone();
        Ok(Windowed::new(self, spec)?)
    }
}
