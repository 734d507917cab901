"""Configuration of the ``vdd`` LeRobot policy type (:class:`VddConfig`)."""

from __future__ import annotations

from dataclasses import dataclass, field

from lerobot.configs import NormalizationMode, PreTrainedConfig
from lerobot.optim import AdamConfig

#: Feature maps of the Rust crates (``vdd_data::features``) the plugin can invert: the map
#: takes the task's raw observation to the per-step vector the LeRobot teacher saw,
#: ``concat(observation.state, observation.environment_state)``.
SUPPORTED_FEATURE_MAPS = ("identity v1", "position_and_lag v1")


@PreTrainedConfig.register_subclass("vdd")
@dataclass
class VddConfig(PreTrainedConfig):
    """Configuration of a VDD student distilled from a LeRobot ``DiffusionPolicy``.

    The student is a mixture of Gaussian experts saved by the Rust crates (``Moe::save``) and
    run by the ``vdd`` wheel; its windowing and chunking are the teacher's, and
    :func:`lerobot_policy_vdd.convert.convert` copies them from the teacher's ``config.json``.

    Args:
        n_obs_steps: Observation window (the teacher's ``n_obs_steps``); must equal the
            mixture's ``obs_window``.
        horizon: Actions per predicted chunk (the teacher's ``horizon``); must equal the
            mixture's ``action_chunk``.
        n_action_steps: Actions of each chunk executed before predicting again, from index
            ``n_obs_steps - 1`` (LeRobot's ``select_action``); must equal the mixture's
            ``execute_steps``.
        normalization_mapping: The teacher's normalisation per feature type; the processors
            normalise with it and the policy inverts it (see the package README).
        normalizer_eps: The teacher's normaliser ``eps``.
        features: The Rust student's observation feature map (``"name vN"``); the policy maps
            LeRobot's ``observation.state`` / ``observation.environment_state`` to the raw
            observation this map expects (one of :data:`SUPPORTED_FEATURE_MAPS`).
        seed: Seed of the student's random draws (expert picks, sampled actions), set when the
            mixture is loaded; ``reset`` does not reseed (as ``vdd.Policy.reset``).
        teacher_path: Where the teacher directory was when the student was converted (for
            the record only).
    """

    n_obs_steps: int = 2
    horizon: int = 16
    n_action_steps: int = 8

    normalization_mapping: dict[str, NormalizationMode] = field(
        default_factory=lambda: {
            "VISUAL": NormalizationMode.MEAN_STD,
            "STATE": NormalizationMode.MIN_MAX,
            "ENV": NormalizationMode.MIN_MAX,
            "ACTION": NormalizationMode.MIN_MAX,
        }
    )
    normalizer_eps: float = 1e-8

    features: str = "position_and_lag v1"
    seed: int = 0
    teacher_path: str | None = None

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.n_obs_steps < 1:
            raise ValueError(f"n_obs_steps = {self.n_obs_steps}: must be at least 1")
        if self.horizon < 1:
            raise ValueError(f"horizon = {self.horizon}: must be at least 1")
        room = self.horizon - (self.n_obs_steps - 1)
        if not 1 <= self.n_action_steps <= room:
            raise ValueError(
                f"n_action_steps = {self.n_action_steps}: must be between 1 and "
                f"horizon - n_obs_steps + 1 = {room} (chunks are executed from index n_obs_steps - 1)"
            )
        if self.features not in SUPPORTED_FEATURE_MAPS:
            raise ValueError(
                f"features = {self.features!r}: the plugin inverts only {', '.join(SUPPORTED_FEATURE_MAPS)}"
            )

    def get_optimizer_preset(self) -> AdamConfig:
        """An Adam preset for LeRobot's trainer; the student is not trained in PyTorch (its
        ``forward`` raises), so this is never used to fit it."""
        return AdamConfig(lr=1e-4)

    def get_scheduler_preset(self) -> None:
        """No scheduler: the student is distilled by the Rust crates, not trained here."""
        return None

    def validate_features(self) -> None:
        """State-only policies: ``observation.state`` and/or ``observation.environment_state``,
        no images (the Rust student has no image encoder)."""
        if self.image_features:
            raise ValueError(
                f"image inputs are not supported by the vdd policy: {sorted(self.image_features)}"
            )
        if self.robot_state_feature is None and self.env_state_feature is None:
            raise ValueError(
                "the vdd policy needs observation.state and/or observation.environment_state among its inputs"
            )
        if self.action_feature is None:
            raise ValueError("the vdd policy needs an `action` output feature")

    @property
    def observation_delta_indices(self) -> list[int]:
        """The observation window, as LeRobot's diffusion policy: ``t - n_obs_steps + 1 .. t``."""
        return list(range(1 - self.n_obs_steps, 1))

    @property
    def action_delta_indices(self) -> list[int]:
        """The predicted chunk, as LeRobot's diffusion policy: from ``t - n_obs_steps + 1``."""
        return list(range(1 - self.n_obs_steps, 1 - self.n_obs_steps + self.horizon))

    @property
    def reward_delta_indices(self) -> None:
        """Rewards are not used."""
        return None

    def observation_keys(self) -> list[str]:
        """The observation features in the order the teacher concatenated them per step:
        ``observation.state`` first, then ``observation.environment_state`` (as LeRobot's
        ``DiffusionModel`` builds its global conditioning)."""
        keys = []
        if self.robot_state_feature is not None:
            keys.append("observation.state")
        if "observation.environment_state" in (self.input_features or {}):
            keys.append("observation.environment_state")
        return keys
