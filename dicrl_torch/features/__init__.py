"""Feature bases ``φ``: fixed, parameter-free maps from states to bounded features
(the :class:`~dicrl_torch.features.base.Basis` protocol). The grid world's are
:mod:`dicrl_torch.features.bases`, the drone arena's :mod:`dicrl_torch.features.drone`;
those of any continuous multi-agent environment, exported here, are
:mod:`dicrl_torch.features.continuous`.
"""

from .continuous import (
    ContinuousFeatureBasis,
    ModuleBasis,
    PositionCellBasis,
    RandomFourierBasis,
)

__all__ = [
    "ContinuousFeatureBasis",
    "ModuleBasis",
    "PositionCellBasis",
    "RandomFourierBasis",
]
