"""Attacks: deterministic image attacks (:mod:`~gsw.attacks.ops`) and model attacks (:mod:`~gsw.attacks.model`)
for evaluation, their named tables (:mod:`~gsw.attacks.presets`), and the random differentiable noise layers
of training (:mod:`~gsw.attacks.layers`, imported on its own).

The evaluation names are re-exported here: ``from gsw.attacks import IMAGE_ATTACKS, crop, remove_random``.
Torch-only at import: never loads the compiled rasterizer (the fine-tuning attack imports it when run).
"""

from gsw.attacks import model, ops, presets
from gsw.attacks.model import *  # noqa: F401,F403
from gsw.attacks.ops import *  # noqa: F401,F403
from gsw.attacks.presets import *  # noqa: F401,F403

__all__ = [*ops.__all__, *model.__all__, *presets.__all__]
