"""Reward features of the constrained MPE ``simple_spread``
(:class:`~dicrl_torch.envs.mpe.ConstrainedSpread`).

:class:`LandmarkRewardBasis` maps joint states ``[..., N, d_s]`` (per agent ``x, y,
vx, vy``: what ``ConstrainedSpread.state()`` gives and
:class:`~dicrl_torch.envs.joint.JointAgentEnv` passes on as ``info["state"]``) to
closeness features in ``[0, 1]``:

- ``coverage`` (default), one per landmark ``j``, named ``landmark{j}``:
  ``exp(-min_i ‖p_i − L_j‖ / σ)``, the closeness of the landmark's nearest agent.
  mpe2's own ``simple_spread`` reward is minus the sum over landmarks of that distance;
  a positive weight on every ``landmark{j}`` pays for covering each landmark, with no
  premium for two agents on one. Shared by the team: a coverage feature belongs to no
  agent (``agent_shares``: ``1 / N`` each).
- ``closeness``, one per agent ``i`` and landmark ``j``, named ``agent{i}/landmark{j}``:
  ``exp(-‖p_i − L_j‖ / σ)``, agent ``i``'s own (``agent_shares``: a one-hot row), for
  per-agent critics (:mod:`dicrl_torch.solvers.sac.decomposed`) and for experts whose
  agents have fixed landmarks.

Exponential closeness rather than linear: it peaks sharply at the landmark, so that
sitting *on* it pays clearly more than hovering near it (the drones' reward basis made
the same choice, docs/drones.md). ``σ`` trades that peak against the gradient far from
the landmarks: the default 0.6 (6 success radii) gives a SAC warm-up from the start
region a usable signal; 0.3 did markedly less well.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from dicrl_torch.features.continuous import ContinuousFeatureBasis, check_position_columns

__all__ = ["FEATURE_KINDS", "LandmarkRewardBasis"]

FEATURE_KINDS: tuple[str, ...] = ("coverage", "closeness")
"""The feature groups :class:`LandmarkRewardBasis` can hold, in the order they come."""


class LandmarkRewardBasis(ContinuousFeatureBasis):
    """Closeness of agents to fixed landmarks (module docstring), ``l`` features in
    ``[0, 1]`` of joint states ``[..., N, d_s]``.

    Features, in this order: ``coverage`` gives ``M`` (one per landmark), ``closeness``
    ``N M`` (agent-major: agent 0's ``M``, then agent 1's, ...). ``max_value = 1``.

    Args:
        n_agents: ``N``.
        landmarks: ``[M, 2]`` landmark positions (e.g. ``SpreadLayout.landmarks``); None:
            the default layout's for ``n_agents``
            (:class:`~dicrl_torch.envs.mpe.SpreadLayout`).
        sigma: the length scale ``σ`` of ``exp(-d / σ)`` (default 0.6, in the arena's
            units: 6 success radii; module docstring).
        features: which groups, a subset of :data:`FEATURE_KINDS` (default
            ``("coverage",)``).
        position_columns: the state components holding ``x`` and ``y`` (default 0, 1).
        state_dim: when given, inputs must have this ``d_s`` (4 for ConstrainedSpread).

    Raises:
        ValueError: bad arguments (naming the value and the fix).
    """

    game = "mpe_spread"  # its default landmarks are the spread's layout

    def __init__(self, *, n_agents: int, landmarks: Any = None, sigma: float = 0.6,
                 features: Sequence[str] = ("coverage",),
                 position_columns: Sequence[int] = (0, 1),
                 state_dim: int | None = None) -> None:
        super().__init__()
        if isinstance(n_agents, bool) or not isinstance(n_agents, int | np.integer) \
                or n_agents < 1:
            raise ValueError(f"n_agents must be a positive int, got {n_agents!r}.")
        self.n_agents = int(n_agents)
        if state_dim is not None and (isinstance(state_dim, bool) or not isinstance(
                state_dim, int | np.integer) or state_dim < 2):
            raise ValueError(f"state_dim must be None or an int >= 2, got {state_dim!r}.")
        self.state_dim = None if state_dim is None else int(state_dim)
        if landmarks is None:
            from dicrl_torch.envs.mpe import SpreadLayout  # the env's own defaults

            landmarks = SpreadLayout(n_agents=self.n_agents).landmarks
        lm = np.asarray(landmarks, dtype=np.float64)
        if lm.ndim != 2 or lm.shape[1] != 2 or len(lm) < 1 or not np.isfinite(lm).all():
            raise ValueError(f"landmarks must be [M, 2] finite points (x, y), got "
                             f"{landmarks!r}.")
        if isinstance(sigma, bool) or not isinstance(sigma, int | float | np.floating) \
                or not np.isfinite(sigma) or sigma <= 0:
            raise ValueError(f"sigma must be a positive length, got {sigma!r}.")
        self.sigma = float(sigma)
        kinds = [features] if isinstance(features, str) else list(features)
        unknown = [k for k in kinds if k not in FEATURE_KINDS]
        if not kinds or unknown or len(set(kinds)) != len(kinds):
            raise ValueError(f"features must be distinct names among {list(FEATURE_KINDS)}, "
                             f"got {features!r}; e.g. features=['coverage'].")
        # Canonical order, whatever order they were given in: names fix the layout.
        self.features = tuple(k for k in FEATURE_KINDS if k in kinds)
        self.position_columns = check_position_columns(position_columns, self.state_dim)
        self.landmarks = tuple(map(tuple, lm.tolist()))
        m = len(lm)
        self.names = []
        if "coverage" in self.features:
            self.names += [f"landmark{j}" for j in range(m)]
        if "closeness" in self.features:
            self.names += [f"agent{i}/landmark{j}" for i in range(self.n_agents)
                           for j in range(m)]
        self.max_value = 1.0
        self.fix_hint = "this is a bug of LandmarkRewardBasis (exp(-d/σ) lies in (0, 1])"
        # Non-persistent: the constructor's arguments rebuild them.
        self.register_buffer("_landmarks", torch.from_numpy(lm), persistent=False)
        self.register_buffer("_columns", torch.tensor(self.position_columns),
                             persistent=False)

    def distances(self, states: torch.Tensor) -> torch.Tensor:
        """``[..., N, M]`` distance of each agent to each landmark, for checked states
        ``[..., N, d_s]``."""
        if max(self.position_columns) >= states.shape[-1]:
            raise ValueError(f"{self.label}: position_columns {self.position_columns} do not "
                             f"fit states with d_s={states.shape[-1]} components.")
        pos = states.index_select(-1, self._columns)  # [..., N, 2]
        diff = pos.unsqueeze(-2) - self._landmarks.to(states.dtype)  # [..., N, M, 2]
        return torch.linalg.vector_norm(diff, dim=-1)

    def compute(self, states: torch.Tensor) -> torch.Tensor:
        """``[..., N, d_s]`` -> ``[..., l]``: coverage ``[..., M]`` then closeness
        ``[..., N M]`` (agent-major), as the names say."""
        close = torch.exp(-self.distances(states) / self.sigma)  # [..., N, M]
        parts = []
        if "coverage" in self.features:
            # The nearest agent is the closest one: max of closeness over agents.
            parts.append(close.amax(-2))  # [..., M]
        if "closeness" in self.features:
            parts.append(close.flatten(-2))  # [..., N M]
        return torch.cat(parts, -1)

    def extra_repr(self) -> str:
        return (f"n_agents={self.n_agents}, landmarks={len(self.landmarks)}, "
                f"sigma={self.sigma}, features={list(self.features)}")
