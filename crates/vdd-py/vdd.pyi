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
from typing import Any, Callable, Iterable, Mapping, Optional, Sequence, Tuple, Union

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
    def save_pretrained(self, out: Path, teacher_dir: Path, seed: int = 0) -> None:
        """Writes a LeRobot policy directory (``--policy.type=vdd``: ``config.json``,
        ``model.safetensors``, the teacher's processors) through the ``lerobot_policy_vdd``
        plugin's converter (``lerobot-vdd-convert``); ``teacher_dir`` is the LeRobot
        ``DiffusionPolicy`` directory the student was distilled from. Raises ``ImportError``
        when the plugin (crates/vdd-py/lerobot_policy_vdd, with lerobot and torch) is not
        installed: then ``save`` the student and run ``lerobot-vdd-convert --student FILE
        --teacher DIR --out DIR`` where it is."""
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
    """A learned diffusion teacher that runs in Rust: a DDPM or BESO teacher saved by the crates
    (``vdd-diffusion``), or a 1-D U-Net diffusion policy imported from PyTorch (LeRobot's
    ``DiffusionPolicy``, diffusion_policy's; ``kind == 'unet1d'``). Usable as the ``score_fn``
    of :func:`distill` (then it runs in Rust, without Python calls).

    An imported teacher's state is an *observation window* (``obs_window`` raw per-step
    observations of ``obs_dim`` entries, oldest first, after its feature map and observation
    map: ``state_dim = obs_window * (mapped obs_dim)``) and its action a whole *chunk*
    (``action_chunk`` per-step actions of ``step_action_dim`` entries, step-major:
    ``action_dim = action_chunk * step_action_dim``). :meth:`training_windows` builds both from
    a user's episodes. A ``vdd-diffusion`` teacher has ``obs_window == action_chunk == 1``.
    """

    def __call__(self, actions: ArrayLike, states: ArrayLike, levels: ArrayLike) -> F32:
        """The score ``(n, action_dim)`` with respect to **raw** actions ``(n, action_dim)`` (an
        imported teacher: raw chunks) at **raw** states ``(n, state_dim)`` (an imported
        teacher: observation windows as :meth:`training_windows` builds them) and noise levels
        ``(n,)`` in the teacher's own convention (``noise_convention``; for an imported U-Net
        diffusers' steps ``t`` in ``noise_range == (1, N)``). The teacher's normalisers are
        applied inside and the score is carried back to raw units (divided by the action
        normaliser's scale): the units :func:`distill` uses."""
    def training_windows(
        self, observations: Sequence[ArrayLike], actions: Sequence[ArrayLike]
    ) -> Tuple[F32, F32]:
        """The states and action chunks to distil an imported teacher on, from a user's own
        episodes, as LeRobot's dataset builds this policy's samples with ``delta_timestamps``.

        ``observations[e]`` is episode ``e``'s raw observations ``(T_e, obs_dim)`` (for a
        ``LeRobotDataset``: per frame ``observation.state`` then
        ``observation.environment_state``, concatenated, unless the teacher was imported with
        an ``obs_map``, which then says where each feature comes from), ``actions[e]`` its
        actions ``(T_e, step_action_dim)``. Observations are raw in the sense of the
        teacher's ``features`` map: with ``'identity v1'`` (any policy trained on a user's own
        dataset) they are the dataset's features as they are; a teacher trained by this
        project's script records ``'position_and_lag v1'`` and then takes the task's raw
        observations, the map being applied here (and by the student when it acts). Returns raw ``states (N, state_dim)`` and
        ``chunks (N, action_dim)``, ``N = sum T_e``: for every step ``t`` the window
        ``t - obs_window + 1 .. t`` and the chunk ``t - obs_window + 1 ..`` of ``action_chunk``
        steps, indices clamped to the episode. Pass them as ``distill(teacher, states,
        actions=chunks)``. ``TypeError`` for a ``vdd-diffusion`` teacher."""
    def sample(self, states: ArrayLike, seed: int = 0) -> F32:
        """Actions ``(n, action_dim)`` drawn by the teacher's own sampler (an imported
        teacher's: ``sampler``) at raw states ``(n, state_dim)``, in raw units (an imported
        teacher: raw chunks at observation windows); the same ``seed``, the same actions."""
    def save(self, path: Path) -> None:
        """Saves an imported teacher as one teacher file (as ``cargo xtask import`` writes it,
        its observation map and sampler included); :func:`load_teacher` reads it back."""
    def set_sampler(self, sampler: str) -> None:
        """The sampler an imported teacher acts (and samples for :func:`distill`) with from
        now on: ``'ddpm'`` (every trained step), ``'ddpm:N'`` or ``'ddim:N'``. Its score does
        not depend on it."""
    @property
    def action_dim(self) -> int:
        """Width of the teacher's action (a whole chunk for an imported teacher)."""
    @property
    def state_dim(self) -> int:
        """Width of the teacher's state (a whole observation window for an imported teacher)."""
    @property
    def obs_dim(self) -> int:
        """Width of one raw per-step observation."""
    @property
    def step_action_dim(self) -> int:
        """Width of one per-step action."""
    @property
    def obs_window(self) -> int:
        """Observations per state (LeRobot's ``n_obs_steps``; 1 for ``vdd-diffusion``)."""
    @property
    def action_chunk(self) -> int:
        """Actions per chunk (LeRobot's ``horizon``; 1 for ``vdd-diffusion``)."""
    @property
    def execute_steps(self) -> int:
        """Actions of a chunk executed before the next prediction (``n_action_steps``)."""
    @property
    def chunk_start(self) -> int:
        """Index of the chunk's first executed action (``n_obs_steps - 1`` for LeRobot)."""
    @property
    def sampler(self) -> Optional[str]:
        """An imported teacher's sampler (``'ddpm'``, ``'ddpm:N'``, ``'ddim:N'``), else None."""
    @property
    def obs_map(self) -> Optional[str]:
        """An imported teacher's observation map (``'key=i,j,...;...'``), else None."""
    @property
    def features(self) -> Optional[str]:
        """An imported teacher's observation feature map (``'name vN'``), else None."""
    @property
    def noise_range(self) -> Optional[Tuple[float, float]]:
        """The noise levels the teacher was trained on (``(1, N)`` for an imported U-Net)."""
    @property
    def kind(self) -> str:
        """``'ddpm'`` or ``'beso'`` (``vdd-diffusion``), ``'unet1d'`` (imported)."""
    @property
    def source(self) -> Optional[str]:
        """An imported teacher's package (``'lerobot'``, ``'diffusion_policy'``), else None."""
    @property
    def noise_convention(self) -> str:
        """``'sigma'`` (VE, BESO) or ``'time'`` (VP: DDPM, imported U-Nets)."""

def load_teacher(
    path: Path,
    seed: int = 0,
    obs_map: Union[None, str, Mapping[str, Iterable[int]]] = None,
    sampler: Optional[str] = None,
) -> Teacher:
    """Loads a teacher: a LeRobot policy directory (as :func:`import_lerobot`), a teacher file
    written by ``cargo xtask import`` or :meth:`Teacher.save`, or a teacher saved by
    ``vdd-diffusion``; ``seed`` seeds its sampler, ``sampler`` (imported teachers) chooses it,
    ``obs_map`` only with a directory. A path that does not exist raises ``ValueError``."""

def import_lerobot(
    path: Path,
    obs_map: Union[None, str, Mapping[str, Iterable[int]]] = None,
    sampler: Optional[str] = None,
    seed: int = 0,
) -> Teacher:
    """Imports a LeRobot ``DiffusionPolicy`` directory (``save_pretrained``'s ``config.json``,
    ``model.safetensors`` and processor files; lerobot >= 0.4, state inputs only: images are
    not supported) as a teacher that runs in Rust.

    ``obs_map`` states where the policy's ``observation.state`` /
    ``observation.environment_state`` come from in the raw per-step observation, as
    ``'observation.state=3..7;observation.environment_state=0..3'`` or
    ``{'observation.state': range(3, 7), 'observation.environment_state': [0, 1, 2]}``
    (``None``: the features concatenated in that order); a map that does not fit the
    features' shapes raises ``ValueError`` naming it. ``sampler`` (``'ddpm'``, ``'ddpm:N'``,
    ``'ddim:N'``) replaces the package's. A path that is not a directory raises ``ValueError``;
    a directory without a valid policy raises :class:`VddError` naming the file and key.
    """

def distill(
    score_fn: Union[Teacher, Callable[[F32, F32, F32], ArrayLike]],
    states: ArrayLike,
    *,
    action_dim: Optional[int] = None,
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
    ``action_dim`` is required for a callable; for a :class:`Teacher` it is the teacher's
    (given, it must match). ``teacher_samples=N`` sets how many teacher actions the plan
    inspects (8192 by default; 2048 for an imported teacher). ``noise_range=(min, max)`` states
    the VE levels a Python ``score_fn`` is trustworthy at (the range it was trained on; ``max``
    may be ``inf``): the plan anneals the noise down to ``min`` instead of below it, and a
    ``noise`` setting outside the range raises :class:`VddError`; a :class:`Teacher` states its
    own.

    **An imported teacher** (:func:`import_lerobot`): ``states`` are raw observation windows
    and ``actions`` raw chunks, from :meth:`Teacher.training_windows` on the user's episodes
    (a width other than ``state_dim`` raises ``ValueError`` saying what the states are). The
    run is wired as Rust's imported-teacher path (``cargo xtask experiment avoiding --teacher
    FILE``): the teacher works in its own normalised chunk space; its denoised chunk is clamped
    to the box of the ``actions`` chunks widened by ``clip_margin`` (0.5 by default, in the
    teacher's normalised units; without ``actions`` this raises ``ValueError``;
    ``clip_margin=None`` distils the raw score, which diverged on the committed fixture);
    the student starts from a mixture fitted to ``teacher_samples`` of the teacher's
    own samples (with the sampler it was given: ``'ddim:10'`` is much faster than the trained
    DDPM schedule); VDD then runs with noise on both sides (``score_at='noised_sample'``),
    levels uniform over the teacher's steps ``[1, 0.3 N]``, batch 32, one sample per state,
    the batch in two chunks on forks of the teacher (both cores), as the recipe's
    ``[vdd.imported]``; ``settings`` override these. Rust's default start, EM on the teacher's
    samples (``vdd.imported_init = "samples"``), is not available from Python. The student emits
    the teacher's whole chunk and acts like the teacher's package: ``act`` takes one raw
    observation and keeps the window and the chunk queue (``obs_window``, ``action_chunk``,
    the executed steps). A teacher imported with an ``obs_map`` is refused (the student cannot
    carry the map yet). To put the student back into LeRobot: ``Policy.save_pretrained(out,
    teacher_dir)`` where the ``lerobot_policy_vdd`` plugin (crates/vdd-py/lerobot_policy_vdd)
    is installed, else ``Policy.save`` and the plugin's ``lerobot-vdd-convert`` later.

    ``defaults='toy'`` starts from the paper's toy settings instead (``VddConfig.toy()``,
    ``MoeConfig.toy()``: exact score, ``sigma = 0``, actions of unit scale near the origin,
    the student's action normaliser only from ``actions``), the behaviour before ``Vdd::auto``
    became the default.
    """
