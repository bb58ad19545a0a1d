"""Features as the SAC solver counts them (see :mod:`dicrl_torch.solvers.sac`).

The bases' features and per-agent shares in numpy, the demonstrations' discounted
feature sums (next-state features, absorbing end) and the fixed observation scaling
:class:`BoxScaler`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from torch import nn

from dicrl_torch.solvers.sac.checks import _check_gamma
from dicrl_torch.solvers.sac.protocol import as_continuous

__all__ = ["BoxScaler", "discounted_demo_feature_sums"]


class BoxScaler(BaseFeaturesExtractor):
    """Maps a bounded ``Box`` observation ``[B, d]`` affinely onto ``[-1, 1]^d`` by its
    known bounds (a fixed map, nothing learned or estimated): positions spanning metres
    and velocities spanning a fraction of that would otherwise differ in range several
    times over. Entries with ``low == high`` map to 0.

    Args:
        observation_space: the ``Box`` whose bounds define the map.
    """

    def __init__(self, observation_space: spaces.Box) -> None:
        super().__init__(observation_space, int(np.prod(observation_space.shape)))
        low = torch.as_tensor(observation_space.low, dtype=torch.float32).flatten()
        high = torch.as_tensor(observation_space.high, dtype=torch.float32).flatten()
        if not (torch.isfinite(low).all() and torch.isfinite(high).all()):
            raise ValueError("BoxScaler needs finite observation bounds; use the default "
                             "extractor for an unbounded Box.")
        half = (high - low) / 2
        self.register_buffer("centre", (high + low) / 2)
        self.register_buffer("half_width", torch.where(half > 0, half, torch.ones_like(half)))

    def forward(self, observations: torch.Tensor) -> torch.Tensor:
        return (observations.flatten(1) - self.centre) / self.half_width


def _basis_dim(basis: Any, name: str) -> int:
    if not isinstance(basis, nn.Module) or not hasattr(basis, "dim"):
        raise ValueError(
            f"{name} must be a feature basis of joint states (an nn.Module with .dim, e.g. "
            f"a dicrl_torch.features.continuous basis), got {type(basis).__name__}."
        )
    return int(basis.dim)


def _agent_shares(basis: nn.Module, name: str, n_agents: int) -> np.ndarray:
    """``[l, N]`` per-agent shares of a basis's features (``agent_shares(N)``)."""
    if not callable(getattr(basis, "agent_shares", None)):
        raise ValueError(
            f"{name} {type(basis).__name__} has no agent_shares(): per-agent critics (and "
            f"success under learned constraints) need to know which agent each feature "
            f"belongs to; subclass dicrl_torch.features.continuous.ContinuousFeatureBasis "
            f"or set per_agent_critics=False."
        )
    shares = np.asarray(torch.as_tensor(basis.agent_shares(n_agents)), dtype=np.float64)
    l = _basis_dim(basis, name)
    if shares.shape != (l, n_agents) or not np.allclose(shares.sum(1), 1.0) \
            or (shares < 0).any():
        raise ValueError(f"{name}.agent_shares() must be [{l}, {n_agents}] non-negative rows "
                         f"summing to 1, got shape {shares.shape}.")
    return shares


def _features(basis: nn.Module, states: np.ndarray) -> np.ndarray:
    """``basis`` on float64 joint states ``[..., N, d_s]`` -> float64 numpy ``[..., l]``."""
    with torch.no_grad():
        return basis(torch.from_numpy(np.array(states, dtype=np.float64))).cpu().numpy()


def discounted_demo_feature_sums(demos: Any, basis: nn.Module, gamma: float,
                                 *, absorbing: bool = True) -> torch.Tensor:
    """Per episode ``Σ_t γ^t φ(s_{t+1})`` over its ``lengths`` steps, as the solver counts
    its rollouts.

    With ``absorbing`` (the solver's default) the last state of each episode (every agent
    done) is absorbing: its term is ``γ^{L-1} φ(s_L) / (1 - γ)``.

    Args:
        demos: :class:`~dicrl_torch.demos.continuous.ContinuousDemonstrations`
            (``states [m, T+1, N, d_s]``, ``lengths [m]``), or demonstrations with
            ``to_continuous()``.
        basis: a feature basis of joint states with ``l`` features.
        gamma: discount in ``(0, 1)``.
        absorbing: treat the final state as absorbing (see the package docstring).

    Returns:
        ``[m, l]`` float64.
    """
    gamma = _check_gamma(gamma)
    _basis_dim(basis, "basis")
    demos = as_continuous(demos)
    phi = torch.as_tensor(_features(basis, demos.states[:, 1:]))  # [m, T, l]
    T = phi.shape[1]
    lengths = torch.from_numpy(np.array(demos.lengths))
    t = torch.arange(T)
    w = gamma ** t.double() * (t < lengths[:, None])  # [m, T]
    if absorbing:
        last = (t == lengths[:, None] - 1)
        w = torch.where(last, w / (1.0 - gamma), w)
    return torch.einsum("mt,mtl->ml", w, phi)
