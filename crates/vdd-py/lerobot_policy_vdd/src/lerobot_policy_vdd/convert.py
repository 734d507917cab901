"""Builds a LeRobot ``vdd`` policy directory from a distilled student file and its LeRobot
teacher directory (:func:`convert`, command ``lerobot-vdd-convert``)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from lerobot.configs import PreTrainedConfig
from lerobot.policies.factory import make_pre_post_processors
from lerobot.processor.normalize_processor import NormalizerProcessorStep, UnnormalizerProcessorStep

from .configuration_vdd import VddConfig
from .modeling_vdd import VddPolicy

#: The file the project's training script writes beside LeRobot's files to record the task's
#: feature map (``vdd_import::FEATURES_FILE``).
FEATURES_FILE = "vdd_features.json"


def _normalizer(pipeline, cls):
    steps = [s for s in pipeline.steps if isinstance(s, cls)]
    if len(steps) != 1:
        raise ValueError(f"expected one {cls.__name__} in {pipeline.name}, found {len(steps)}")
    return steps[0]


def convert(student: str | Path, teacher_dir: str | Path, out: str | Path, *, seed: int = 0) -> VddPolicy:
    """Writes ``out``, a LeRobot directory of the ``vdd`` policy type, and returns the policy.

    ``student`` is the mixture file the Rust crates saved (``cargo xtask experiment
    --teacher``'s ``models/*.safetensors``), ``teacher_dir`` the LeRobot ``DiffusionPolicy``
    directory it was distilled from. The policy's windowing, chunking, features and
    normalisation come from the teacher's ``config.json``, its statistics from the teacher's
    normaliser state file; the teacher's processors are saved into ``out`` by LeRobot's own
    ``save_pretrained`` (the same statistics). ``seed`` seeds the student's random draws.
    """
    student, teacher_dir, out = Path(student), Path(teacher_dir), Path(out)
    if not student.is_file():
        raise FileNotFoundError(f"no student file at {student}")
    if not (teacher_dir / "config.json").is_file():
        raise FileNotFoundError(f"no LeRobot teacher directory at {teacher_dir} (config.json missing)")
    teacher_cfg = PreTrainedConfig.from_pretrained(teacher_dir)
    for key in ("n_obs_steps", "horizon", "n_action_steps", "normalization_mapping"):
        if not hasattr(teacher_cfg, key):
            raise ValueError(f"the teacher's config ({teacher_cfg.type}) has no {key!r}")
    pre, post = make_pre_post_processors(teacher_cfg, pretrained_path=str(teacher_dir))
    norm = _normalizer(pre, NormalizerProcessorStep)
    unnorm = _normalizer(post, UnnormalizerProcessorStep)
    stats = norm.state_dict()
    for key, value in unnorm.state_dict().items():
        if key in stats and not (stats[key] == value).all():
            raise ValueError(f"the teacher's pre- and post-processor disagree on {key}")
        stats.setdefault(key, value)

    features = "identity v1"
    features_file = teacher_dir / FEATURES_FILE
    if features_file.is_file():
        recorded = json.loads(features_file.read_text())
        features = f"{recorded['name']} v{recorded['version']}"

    config = VddConfig(
        n_obs_steps=teacher_cfg.n_obs_steps,
        horizon=teacher_cfg.horizon,
        n_action_steps=teacher_cfg.n_action_steps,
        input_features=dict(teacher_cfg.input_features),
        output_features=dict(teacher_cfg.output_features),
        normalization_mapping={t.value: m for t, m in norm.norm_map.items()},
        normalizer_eps=norm.eps,
        features=features,
        seed=seed,
        device="cpu",
        push_to_hub=False,
        teacher_path=str(teacher_dir),
    )
    policy = VddPolicy(config)
    policy.load_stats(stats)
    policy.load_mixture(student)
    policy.save_pretrained(out)
    pre.save_pretrained(out)
    post.save_pretrained(out)
    return policy


def main(argv: list[str] | None = None) -> int:
    """``lerobot-vdd-convert --student FILE --teacher DIR --out DIR [--seed N]``."""
    p = argparse.ArgumentParser(description=convert.__doc__.splitlines()[0])
    p.add_argument("--student", required=True, help="the distilled mixture file (Moe::save)")
    p.add_argument("--teacher", required=True, help="the LeRobot DiffusionPolicy directory")
    p.add_argument("--out", required=True, help="the LeRobot directory to write")
    p.add_argument("--seed", type=int, default=0, help="seed of the student's random draws")
    args = p.parse_args(argv)
    try:
        policy = convert(args.student, args.teacher, args.out, seed=args.seed)
    except (FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    s = policy.student
    print(
        f"wrote {args.out}: vdd policy of {s.num_experts} experts, window {s.obs_window}, "
        f"chunk {s.action_chunk}, features {s.features}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
