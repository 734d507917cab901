"""The ``vdd`` LeRobot policy (:class:`VddPolicy`): a distilled mixture of experts run by the
Rust ``vdd`` wheel behind LeRobot's ``PreTrainedPolicy`` interface."""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import torch
from huggingface_hub.constants import SAFETENSORS_SINGLE_FILE
from lerobot.configs import NormalizationMode
from lerobot.configs.types import FeatureType
from lerobot.policies.pretrained import PreTrainedPolicy
from lerobot.processor.normalize_processor import NormalizerProcessorStep
from safetensors import safe_open
from safetensors.torch import load_file, save_file
from torch import Tensor

from .configuration_vdd import VddConfig

#: The tensor of ``model.safetensors`` holding the Rust mixture file (``Moe::save``), byte for
#: byte, as ``uint8``.
MIXTURE_KEY = "vdd.mixture"
#: Prefix of the tensors of ``model.safetensors`` holding the teacher's normaliser statistics
#: (``normalizer.<feature>.<stat>``, the keys of LeRobot's normaliser state files).
STATS_PREFIX = "normalizer."
#: Stats each normalisation mode needs (LeRobot's ``_NormalizationMixin._apply_transform``).
_NEEDED_STATS = {
    NormalizationMode.MEAN_STD: ("mean", "std"),
    NormalizationMode.MIN_MAX: ("min", "max"),
    NormalizationMode.QUANTILES: ("q01", "q99"),
    NormalizationMode.QUANTILE10: ("q10", "q90"),
}


_VDD_HINT = (
    "the vdd policy needs the `vdd` wheel of the VDD repository (crates/vdd-py): build it with "
    "`maturin build --release` in crates/vdd-py and pip install the wheel (PyPI's `vdd` is "
    "another project)"
)


def _import_vdd():
    try:
        import vdd  # noqa: PLC0415
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError(_VDD_HINT) from e
    if not hasattr(vdd, "Policy") or not hasattr(vdd, "VddError"):
        raise ImportError(f"`vdd` imported from {getattr(vdd, '__file__', '?')} is not ours: {_VDD_HINT}")
    return vdd


def raw_observation(per_step: np.ndarray, features: str) -> np.ndarray:
    """The task's raw observation whose feature map ``features`` gives ``per_step``, the
    LeRobot teacher's per-step vector ``concat(observation.state,
    observation.environment_state)`` (rows of ``per_step``).

    ``identity v1``: the vector itself. ``position_and_lag v1`` (``(d, c) -> (c, d - c)``):
    ``per_step = (c, lag)`` gives ``(lag + c, c)``; the Rust student maps it back to
    ``(c, (lag + c) - c)``, which is ``lag`` up to one float32 rounding of ``lag + c``.
    """
    per_step = np.ascontiguousarray(per_step, dtype=np.float32)
    if features == "identity v1":
        return per_step
    if features == "position_and_lag v1":
        dim = per_step.shape[-1]
        if dim % 2:
            raise ValueError(
                f"the position_and_lag feature map needs an even observation width, got {dim}"
            )
        k = dim // 2
        c, lag = per_step[..., :k], per_step[..., k:]
        return np.ascontiguousarray(np.concatenate([lag + c, c], axis=-1), dtype=np.float32)
    raise ValueError(f"feature map {features!r} cannot be inverted by the vdd plugin")


class VddPolicy(PreTrainedPolicy):
    """A VDD student (a mixture of Gaussian experts distilled from a LeRobot
    ``DiffusionPolicy``) as a LeRobot policy.

    Like LeRobot's ``DiffusionPolicy`` it takes and returns *normalised* tensors: the
    pre-processor normalises observations with the teacher's statistics and the
    post-processor unnormalises actions. Inside, :meth:`select_action` undoes the
    normalisation (with the same statistics and LeRobot's own formulas), maps the per-step
    vector ``concat(observation.state, observation.environment_state)`` to the task's raw
    observation (:func:`raw_observation`) and calls the Rust policy's ``act_batch``, which keeps
    LeRobot's observation queue and action chunking: the first observation repeated
    ``n_obs_steps`` times at an episode's start, a chunk of ``horizon`` actions predicted from the
    last ``n_obs_steps`` observations, executed from index ``n_obs_steps - 1`` for
    ``n_action_steps`` steps. Its raw action is normalised again for the post-processor.

    ``model.safetensors`` holds the Rust mixture file byte for byte (tensor
    :data:`MIXTURE_KEY`) and the teacher's normaliser statistics (:data:`STATS_PREFIX`).
    Build one from a student file with :func:`lerobot_policy_vdd.convert.convert`.
    """

    config_class = VddConfig
    name = "vdd"

    def __init__(
        self,
        config: VddConfig,
        dataset_stats: dict[str, dict[str, Tensor]] | None = None,
        **kwargs: Any,
    ):
        """An empty policy of ``config`` (no mixture yet: load one with ``from_pretrained``
        or :meth:`load_mixture`); ``dataset_stats`` are the normaliser statistics
        (``{feature: {stat: tensor}}``), else those loaded with the mixture."""
        super().__init__(config)
        config.validate_features()
        self.config = config
        self._student = None
        self._mixture: bytes | None = None
        self._deploy: dict[str, Any] = {}
        self._batch_size: int | None = None
        features = dict(config.input_features or {})
        features.update(config.output_features or {})
        self._normalizer = NormalizerProcessorStep(
            features=features,
            norm_map=dict(config.normalization_mapping),
            stats=None,
            eps=config.normalizer_eps,
        )
        if dataset_stats:
            self.load_stats(
                {
                    f"{key}.{stat}": torch.as_tensor(np.asarray(value), dtype=torch.float32)
                    for key, sub in dataset_stats.items()
                    for stat, value in sub.items()
                }
            )

    # ----------------------------------------------------------------------------- loading

    def load_stats(self, flat: dict[str, Tensor]) -> None:
        """Sets the normaliser statistics from LeRobot's flat ``{"feature.stat": tensor}``
        layout (a normaliser processor's state file); an error naming a feature whose
        statistics are missing for its normalisation mode."""
        self._normalizer.load_state_dict({k: v.detach().cpu() for k, v in flat.items()})
        for key, ft in self._normalizer.features.items():
            mode = self._normalizer.norm_map.get(ft.type, NormalizationMode.IDENTITY)
            have = self._normalizer._tensor_stats.get(key, {})
            missing = [s for s in _NEEDED_STATS.get(mode, ()) if s not in have]
            if missing:
                raise ValueError(
                    f"normaliser statistics of {key!r} ({mode.value}) lack {missing}; have {sorted(have)}"
                )
            for stat in _NEEDED_STATS.get(mode, ()):
                if tuple(have[stat].shape) != tuple(ft.shape):
                    raise ValueError(
                        f"normaliser statistic {key}.{stat} has shape {tuple(have[stat].shape)}, "
                        f"the feature {tuple(ft.shape)}"
                    )

    def stats_state_dict(self) -> dict[str, Tensor]:
        """The normaliser statistics in LeRobot's flat layout."""
        return self._normalizer.state_dict()

    def load_mixture(self, mixture: bytes | str | os.PathLike) -> None:
        """Loads the Rust student (a file saved by ``Moe::save`` / ``vdd.Policy.save``, or its
        bytes) and checks it against the configuration: window, chunk, executed steps, chunk
        start, feature map and dimensions. Seeds it with ``config.seed``."""
        vdd = _import_vdd()
        if not isinstance(mixture, (bytes, bytearray)):
            path = Path(mixture)
            if not path.is_file():
                raise FileNotFoundError(f"no student file at {path}")
            mixture = path.read_bytes()
        mixture = bytes(mixture)
        fd, tmp = tempfile.mkstemp(suffix=".safetensors")
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(mixture)
            try:
                student = vdd.Policy.load(tmp)
                with safe_open(tmp, framework="np") as f:
                    meta = f.metadata() or {}
            except (vdd.VddError, ValueError, OSError) as e:
                raise ValueError(f"not a loadable vdd student: {e}") from e
        finally:
            os.unlink(tmp)
        deploy = json.loads(meta.get("deploy_spec", "{}") or "{}")
        self._check_student(student, deploy)
        student.seed(int(self.config.seed))
        self._student, self._mixture, self._deploy = student, mixture, deploy
        self._batch_size = None

    def _check_student(self, student, deploy: dict[str, Any]) -> None:
        cfg = self.config
        obs_dim = sum(cfg.input_features[k].shape[0] for k in cfg.observation_keys())
        act_dim = cfg.action_feature.shape[0]
        want = {
            "obs_window (n_obs_steps)": (student.obs_window, cfg.n_obs_steps),
            "action_chunk (horizon)": (student.action_chunk, cfg.horizon),
            "execute_steps (n_action_steps)": (deploy.get("execute_steps"), cfg.n_action_steps),
            "chunk_start (n_obs_steps - 1)": (deploy.get("chunk_start", 0), cfg.n_obs_steps - 1),
            "features": (student.features, cfg.features),
            "obs_dim (state + environment_state)": (student.obs_dim, obs_dim),
            "action_dim": (student.action_dim, act_dim),
        }
        bad = [f"{k}: student {s!r}, config {c!r}" for k, (s, c) in want.items() if s != c]
        if bad:
            raise ValueError("the student does not fit the policy's configuration: " + "; ".join(bad))

    @property
    def student(self):
        """The Rust ``vdd.Policy`` this policy runs (an error if none is loaded)."""
        if self._student is None:
            raise RuntimeError(
                "this vdd policy has no student loaded: use VddPolicy.from_pretrained(dir) on a "
                "directory written by lerobot_policy_vdd.convert, or load_mixture(path)"
            )
        return self._student

    def _save_pretrained(self, save_directory: Path, state_dict: dict[str, Tensor] | None = None) -> None:
        """Writes ``config.json`` and ``model.safetensors`` (the mixture's bytes and the
        normaliser statistics); ``state_dict`` is not used (the weights are the mixture's)."""
        if self._mixture is None:
            raise RuntimeError("nothing to save: this vdd policy has no student loaded")
        self.config._save_pretrained(save_directory)
        tensors = {MIXTURE_KEY: torch.frombuffer(bytearray(self._mixture), dtype=torch.uint8)}
        for key, value in self.stats_state_dict().items():
            tensors[STATS_PREFIX + key] = value.detach().cpu().contiguous()
        save_file(
            tensors,
            str(Path(save_directory) / SAFETENSORS_SINGLE_FILE),
            metadata={"format": "pt", "lerobot_policy_vdd": "1"},
        )

    @classmethod
    def _load_as_safetensor(cls, model: "VddPolicy", model_file: str, map_location: str, strict: bool):
        """Loads ``model.safetensors`` written by :meth:`_save_pretrained` (called by LeRobot's
        ``from_pretrained``)."""
        if not os.path.isfile(model_file):
            raise FileNotFoundError(f"no {SAFETENSORS_SINGLE_FILE} at {model_file}")
        tensors = load_file(model_file)
        if MIXTURE_KEY not in tensors:
            raise ValueError(
                f"{model_file} is not a vdd policy (no {MIXTURE_KEY!r} tensor): build one from a "
                "student file with `lerobot-vdd-convert`"
            )
        stats = {k[len(STATS_PREFIX) :]: v for k, v in tensors.items() if k.startswith(STATS_PREFIX)}
        model.load_stats(stats)
        model.load_mixture(tensors[MIXTURE_KEY].numpy().tobytes())
        return model

    # ------------------------------------------------------------------------------ acting

    def get_optim_params(self) -> dict:
        """The (empty) parameters: the student is not trained in PyTorch."""
        return self.parameters()

    def reset(self) -> None:
        """Forgets the observation queue and the action chunk (at an episode's start); does
        not reseed."""
        if self._student is not None:
            self._student.reset()
        self._batch_size = None

    def forward(self, batch: dict[str, Tensor]) -> tuple[Tensor, dict | None]:
        """Not supported: the student is distilled by the Rust crates (``cargo xtask
        experiment``, ``vdd.distill``), not trained by LeRobot."""
        raise NotImplementedError(
            "the vdd policy is not trained in PyTorch: distil it with `cargo xtask experiment` or "
            "`vdd.distill`, then convert it with `lerobot-vdd-convert`"
        )

    def _per_step(self, batch: dict[str, Tensor], window: bool) -> tuple[np.ndarray, torch.device]:
        """The raw per-step observations ``(B, [n_obs_steps,] obs_dim)`` of a normalised batch."""
        parts, device, lead = [], None, None
        for key in self.config.observation_keys():
            if key not in batch:
                raise ValueError(
                    f"the batch lacks {key!r} (has {sorted(batch)}); the vdd policy needs "
                    f"{self.config.observation_keys()}"
                )
            t = torch.as_tensor(batch[key])
            dim = self.config.input_features[key].shape[0]
            ndim = 3 if window else 2
            if not window and t.ndim == 1:
                t = t.unsqueeze(0)
            shape_ok = t.ndim == ndim and t.shape[-1] == dim
            if window:
                shape_ok = shape_ok and t.shape[1] == self.config.n_obs_steps
            if not shape_ok:
                want = f"(B, {self.config.n_obs_steps}, {dim})" if window else f"(B, {dim})"
                raise ValueError(f"{key!r} has shape {tuple(t.shape)}, expected {want}")
            if lead is not None and t.shape[0] != lead:
                raise ValueError(f"{key!r} has batch size {t.shape[0]}, other features {lead}")
            lead, device = t.shape[0], t.device
            t = t.detach().to("cpu", torch.float32)
            if not torch.isfinite(t).all():
                raise ValueError(f"{key!r} has non-finite values")
            ft_type = self.config.input_features[key].type
            parts.append(self._normalizer._apply_transform(t, key, ft_type, inverse=True))
        per_step = torch.cat(parts, dim=-1).numpy()
        return raw_observation(per_step, self.config.features), device

    def _normalize_action(self, raw: np.ndarray, device: torch.device) -> Tensor:
        a = torch.from_numpy(np.ascontiguousarray(raw, dtype=np.float32))
        a = self._normalizer._apply_transform(a, "action", FeatureType.ACTION, inverse=False)
        return a.to(device)

    @torch.no_grad()
    def select_action(self, batch: dict[str, Tensor], **kwargs: Any) -> Tensor:
        """One normalised action ``(B, action_dim)`` for a normalised batch of observations
        ``{"observation.state": (B, ds), "observation.environment_state": (B, de)}`` (one row per
        environment, the same rows until :meth:`reset`); ``noise`` and other keywords are
        ignored."""
        student = self.student
        raw, device = self._per_step(batch, window=False)
        b = raw.shape[0]
        if self._batch_size is not None and b != self._batch_size:
            raise ValueError(
                f"batch size changed from {self._batch_size} to {b} without reset(): each row is an "
                "environment with its own observation queue"
            )
        self._batch_size = b
        return self._normalize_action(student.act_batch(raw), device)

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor], **kwargs: Any) -> Tensor:
        """The executed part of a chunk ``(B, n_action_steps, action_dim)``, normalised, for
        windows ``{key: (B, n_obs_steps, dim)}`` (stateless). Deterministic: the mean of each
        window's most likely expert, whatever act mode the student file saved (which
        :meth:`select_action` follows)."""
        raw, device = self._per_step(batch, window=True)
        b, w, d = raw.shape
        log_gating, means, _ = self.student.components(raw.reshape(b, w * d))
        z = np.argmax(log_gating, axis=1)
        chunk = means[np.arange(b), z].reshape(b, self.config.horizon, -1)
        start = self.config.n_obs_steps - 1
        executed = chunk[:, start : start + self.config.n_action_steps]
        return self._normalize_action(executed, device)
