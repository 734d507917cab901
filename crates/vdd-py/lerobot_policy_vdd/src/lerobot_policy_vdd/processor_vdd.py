"""Pre- and post-processors of the ``vdd`` policy type (:func:`make_vdd_pre_post_processors`)."""

from __future__ import annotations

from typing import Any

import torch
from lerobot.processor import PolicyAction, PolicyProcessorPipeline, make_default_pre_post_processors

from .configuration_vdd import VddConfig


def make_vdd_pre_post_processors(
    config: VddConfig,
    dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None,
) -> tuple[
    PolicyProcessorPipeline[dict[str, Any], dict[str, Any]],
    PolicyProcessorPipeline[PolicyAction, PolicyAction],
]:
    """LeRobot's default pipelines, as for its ``DiffusionPolicy``: rename, add a batch
    dimension, move to the device and normalise the observations (pre-processor); unnormalise
    the actions and move them to the CPU (post-processor), with ``config.normalization_mapping``
    and ``dataset_stats``.

    LeRobot calls this for a policy made from scratch; ``from_pretrained`` directories carry
    their own processor files instead (the teacher's, copied by
    :func:`lerobot_policy_vdd.convert.convert`).
    """
    return make_default_pre_post_processors(config, dataset_stats)
