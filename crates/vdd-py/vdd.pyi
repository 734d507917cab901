"""Variational Diffusion Distillation, from Python.

Load, run and export mixture-of-experts policies distilled by the Rust crates, and distil a
teacher that lives in Python (NumPy, PyTorch on a GPU, ...) with the Rust trainer.

Arrays go in as anything NumPy can turn into ``float32`` and come out as ``float32`` NumPy
arrays. The GIL is released while Rust computes (it is taken again only to call a Python
``score_fn``). Invalid arguments raise ``ValueError``; other failures of the Rust side raise
:class:`VddError`; an exception raised by a ``score_fn`` is raised again as itself.

Batches are bounded before anything is allocated: ``act_batch``, ``log_likelihood``,
``components`` and a teacher's score take at most ``2**20`` rows per call (more raise
``ValueError``: split the batch), and a batch whose estimated memory exceeds what the machine
has available raises ``MemoryError``. No call raises ``PanicException``: an internal error of
the Rust side, should one happen, raises ``RuntimeError``.
"""

from os import PathLike
from typing import Any, Callable, Optional, Tuple, Union

import numpy as np
import numpy.typing as npt

__version__: str

ArrayLike = npt.ArrayLike
F32 = npt.NDArray[np.float32]
Path = Union[str, PathLike]

class VddError(Exception):
    """A failure of the Rust side (file I/O, a malformed model, a failed training step)."""

class Policy:
    """A distilled mixture-of-experts policy acting on raw environment observations.

    ``q(a|s) = sum_z q(z|s) N(a; mu_z(s), L_z(s) L_z(s)^T)``. The saved file carries its
    deployment spec: the observation feature map, the observation window and the action chunk.
    ``act`` and ``act_batch`` keep each environment's observation history and action chunk;
    ``components`` and ``log_likelihood`` are stateless and take whole windows
    ``(n, obs_window * obs_dim)`` of raw observations (oldest first) and whole chunks
    ``(n, action_chunk * action_dim)``; for a policy with ``obs_window == action_chunk == 1``
    (the Avoiding students, ``vdd.distill``'s) these are single observations and actions.
    """

    @staticmethod
    def load(path: Path) -> "Policy":
        """Loads a policy saved by the crates (``cargo xtask experiment``) or by ``save``."""
    def act(self, obs: ArrayLike) -> F32:
        """One action ``(action_dim,)`` for one raw observation ``(obs_dim,)``."""
    def act_batch(self, obs: ArrayLike) -> F32:
        """Actions ``(n, action_dim)`` for ``(n, obs_dim)`` raw observations, one row per
        environment (each row keeps its own history and chunk)."""
    def log_likelihood(self, obs: ArrayLike, actions: ArrayLike) -> F32:
        """Exact ``log q(actions | obs)`` ``(n,)`` for raw observation windows and raw
        action chunks."""
    def components(self, obs: ArrayLike) -> Tuple[F32, F32, F32]:
        """The mixture at raw observation windows ``(n, obs_window * obs_dim)``, in raw action
        space: ``(log_gating (n, Z), means (n, Z, A), scale_tril (n, Z, A, A))``,
        ``A = action_chunk * action_dim``.

        To act by hand: pick ``z`` with probability ``exp(log_gating[i, z])`` (or the argmax),
        then take ``means[i, z]`` or sample ``means[i, z] + scale_tril[i, z] @ eps`` with
        ``eps ~ N(0, I)``. A saved act mode with ``hold_steps > 1`` keeps each episode's ``z``
        for that many predictions: do the same by hand.
        """
    def export_onnx(self, path: Path) -> None:
        """Writes an ONNX graph with input ``obs`` ``(n, obs_window * obs_dim)`` and outputs
        ``log_gating``, ``means``, ``scale_tril`` equal to ``components(obs)``."""
    def reset(self) -> None:
        """Forgets observation histories, action chunks and held experts (at an episode's
        start)."""
    def seed(self, seed: int) -> None:
        """Reseeds acting's random draws (expert picks, sampled actions)."""
    def save(self, path: Path) -> None:
        """Saves weights, normalisers, act mode and deployment spec to one file."""
    def rust_us_per_act(
        self, obs: ArrayLike, calls: int = 2000, warmup: int = 100, min_round_ms: float = 20.0
    ) -> float:
        """Rust's own µs per ``act`` call (``vdd_tasks::timing::us_per_action``, the recipes'
        measurement: median of 5 rounds) over the episode ``obs`` ``(T, obs_dim)``, on a copy
        of the policy: the figure to set beside the time of ``act`` measured from Python."""
    @property
    def obs_dim(self) -> int:
        """Dimension of one raw observation."""
    @property
    def action_dim(self) -> int:
        """Dimension of one action."""
    @property
    def num_experts(self) -> int:
        """Number of experts ``Z``."""
    @property
    def obs_window(self) -> int:
        """Raw observations per model input (oldest first)."""
    @property
    def action_chunk(self) -> int:
        """Actions per predicted chunk."""
    @property
    def features(self) -> str:
        """The observation feature map, e.g. ``'position_and_lag v1'``."""

class Teacher:
    """A learned diffusion teacher (DDPM or BESO) saved by the crates; usable as a
    ``score_fn`` of :func:`distill` (then it runs in Rust, without Python calls)."""

    def __call__(self, actions: ArrayLike, states: ArrayLike, levels: ArrayLike) -> F32:
        """The score ``(n, action_dim)`` with respect to raw actions ``(n, action_dim)`` at raw
        states ``(n, state_dim)`` and noise levels ``(n,)`` in the teacher's own normalised
        space and convention (see ``noise_convention``)."""
    @property
    def action_dim(self) -> int: ...
    @property
    def state_dim(self) -> int: ...
    @property
    def kind(self) -> str:
        """``'ddpm'`` or ``'beso'``."""
    @property
    def noise_convention(self) -> str:
        """``'sigma'`` (VE, BESO) or ``'time'`` (VP, DDPM)."""

def load_teacher(path: Path, seed: int = 0) -> Teacher:
    """Loads a teacher saved by ``vdd-diffusion``; ``seed`` seeds its sampler."""

def distill(
    score_fn: Callable[[F32, F32, F32], ArrayLike],
    states: ArrayLike,
    *,
    action_dim: int,
    experts: int = 8,
    iterations: Optional[int] = None,
    seed: int = 0,
    actions: Optional[ArrayLike] = None,
    sample_fn: Optional[Callable[[F32], ArrayLike]] = None,
    **settings: Any,
) -> Policy:
    """Distils a teacher into a mixture of ``experts`` Gaussian experts with the Rust VDD
    trainer, and returns the student.

    ``score_fn(actions, states, sigma)`` gets ``(n, action_dim)``, ``(n, state_dim)`` and
    ``(n,)`` float32 arrays and returns the teacher's score ``(n, action_dim)`` at those noise
    levels (VE sigma). Any callable works: NumPy, or PyTorch on a GPU (convert to and from
    NumPy). A :class:`Teacher` runs in Rust. ``states`` ``(n, state_dim)`` are the raw states
    to distil on; the student normalises them by their mean and standard deviation.
    ``actions`` (optional, ``(n, action_dim)``) are dataset actions; ``sample_fn(states)``
    (optional) returns one teacher action ``(n, action_dim)`` per state row ``(n, state_dim)``
    (finite, or ``ValueError``). ``iterations`` is picked from the teacher unless given: 600
    for a teacher that ignores the state, up to 2400 the more the state decides which
    component an action belongs to.

    The run is set up from the teacher as Rust's ``Vdd::auto`` does (``AutoOptions::new(experts,
    seed)``): actions of the teacher (from ``sample_fn``, else ``actions``, else annealed reverse
    diffusion with ``score_fn`` alone: 200 calls of 8192 rows, at up to 256 of the states; the
    learned gating then trains on all 8192) give the student's normalisers, the noise annealed
    from half their spread over the first 420 iterations (70 % of a 600-iteration run), and
    full-covariance experts with a learned gating started on a mixture fitted to them.

    ``settings`` are then applied to that plan: fields of the trainer's ``VddConfig``
    (``batch_size``, ``vi_samples``, ``noise={'kind': 'uniform', 'min': 0.1, 'max': 1.0}``,
    ``noise_anneal_until=0.5``, ``expert_optimizer={'lr': 1e-3, ...}``, ...) or the student's
    ``MoeConfig`` (``expert_kind='diag'``, ``gating='uniform'``, ``init_std``,
    ``experts_network={'hidden_dim': 64, 'num_blocks': 1, 'activation': 'mish'}``, ...); an
    unknown key raises ``ValueError`` naming it (before the teacher is called).
    ``defaults='toy'`` starts from the paper's toy settings instead (``VddConfig.toy()``,
    ``MoeConfig.toy()``: exact score, ``sigma = 0``, actions of unit scale near the origin,
    the student's action normaliser only from ``actions``), the behaviour before ``Vdd::auto``
    became the default.
    """
