"""dicrl_torch: distributed inverse constrained reinforcement learning (D-ICRL) in PyTorch.

``from dicrl_torch import fit`` is the one high-level entry for your own game
(:func:`dicrl_torch.runs.fit.fit`); everything below it stays importable from its module.
It is imported on first use, so ``import dicrl_torch.envs`` (or any other part) stays
light.
"""

from __future__ import annotations

import importlib
from typing import Any

__all__ = ["FitResult", "fit"]

_LAZY = {"fit": "dicrl_torch.runs.fit", "FitResult": "dicrl_torch.runs.fit"}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'dicrl_torch' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *_LAZY])
