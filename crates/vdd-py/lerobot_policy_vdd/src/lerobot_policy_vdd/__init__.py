"""A VDD-distilled mixture-of-experts student as a LeRobot policy type (``--policy.type=vdd``).

Importing this package registers the configuration class under ``"vdd"`` with LeRobot's
``PreTrainedConfig`` registry; LeRobot's ``register_third_party_plugins`` imports it for you
(it imports every installed distribution whose name starts with ``lerobot_policy_``). LeRobot
then finds :class:`VddPolicy` in :mod:`lerobot_policy_vdd.modeling_vdd` and
:func:`make_vdd_pre_post_processors` in :mod:`lerobot_policy_vdd.processor_vdd` by its naming
convention.

Build a LeRobot directory from a distilled student file and its LeRobot teacher directory with
:func:`lerobot_policy_vdd.convert.convert` (or ``lerobot-vdd-convert``).
"""

from .configuration_vdd import VddConfig
from .modeling_vdd import VddPolicy
from .processor_vdd import make_vdd_pre_post_processors

__all__ = ["VddConfig", "VddPolicy", "make_vdd_pre_post_processors"]
__version__ = "0.1.0"
