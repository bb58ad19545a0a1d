"""The spaces the continuous arenas share (:class:`~dicrl_torch.envs.drones.DroneArena`,
:class:`~dicrl_torch.envs.mpe.ConstrainedSpread`): each agent observes a bounded float32
vector and commands a planar action ``[2]`` in ``[-1, 1]^2`` (the symmetric box SAC
expects)."""

from __future__ import annotations

import numpy as np
from gymnasium import spaces

__all__ = ["PlanarCommandSpaces"]


class PlanarCommandSpaces:
    """The spaces of a :class:`~dicrl_torch.envs.parallel.CheckedParallelEnv` (listed
    before it among the bases) whose constructor sets the float32 observation bounds
    ``_obs_low`` and ``_obs_high``; every agent commands ``[2]`` in ``[-1, 1]^2``."""

    _obs_low: np.ndarray
    _obs_high: np.ndarray

    # ---- spaces (cached per agent by CheckedParallelEnv) ----------------------------
    def _observation_space(self) -> spaces.Box:
        return spaces.Box(low=self._obs_low, high=self._obs_high, dtype=np.float32)

    def _action_space(self) -> spaces.Box:
        return spaces.Box(low=-1.0, high=1.0, shape=(2,), dtype=np.float32)

    def _bounded(self, o: np.ndarray) -> np.ndarray:
        """``o`` as float32 within the observation bounds: the env keeps it inside them,
        the clip only absorbs float32 rounding."""
        return np.clip(o.astype(np.float32), self._obs_low, self._obs_high)
