"""Attacks: deterministic image and model attacks (evaluation), random differentiable noise layers (training).

Torch-only at import: never loads the compiled rasterizer (the fine-tuning attack imports it when run).
"""

from gsw.attacks.ops import *  # noqa: F401,F403
from gsw.attacks.ops import __all__  # noqa: F401
