"""Features of the drone arena as the SAC solver counts them (see :mod:`dicrl_torch.solvers.sac`).

Joint observations from joint states, the bases' features and per-drone shares in numpy,
the demonstrations' discounted feature sums (next-state features, absorbing end) and the
fixed observation scaling :class:`BoxScaler`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from torch import nn

from dicrl_torch.demos.drone_demos import DroneDemonstrations
from dicrl_torch.envs.drones import N_DRONES, door_centres
from dicrl_torch.solvers.sac.checks import _check_gamma

__all__ = ["STATE_SHAPE", "BoxScaler", "discounted_demo_feature_sums", "joint_obs_from_states"]

STATE_SHAPE: tuple[int, int] = (N_DRONES, 4)


class BoxScaler(BaseFeaturesExtractor):
    """Maps a bounded ``Box`` observation ``[B, d]`` affinely onto ``[-1, 1]^d`` by its
    known bounds (a fixed map, nothing learned or estimated): the arena's positions span
    0-10 m and its velocities ±1.5 m/s, so unscaled inputs differ in range by ~7x.
    Entries with ``low == high`` (none in the arena) map to 0.

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
            f"{name} must be a drone feature basis (an nn.Module with .dim, e.g. "
            f"CellOccupancyCostBasis()), got {type(basis).__name__}."
        )
    return int(basis.dim)


def _drone_shares(basis: nn.Module, name: str) -> np.ndarray:
    """``[l, N_DRONES]`` per-drone shares of a basis's features (``drone_shares()``)."""
    if not callable(getattr(basis, "drone_shares", None)):
        raise ValueError(
            f"{name} {type(basis).__name__} has no drone_shares(): per-drone critics need to "
            f"know which drone each feature belongs to; subclass DroneFeatureBasis or set "
            f"per_drone_critics=False."
        )
    shares = np.asarray(torch.as_tensor(basis.drone_shares()), dtype=np.float64)
    l = _basis_dim(basis, name)
    if shares.shape != (l, N_DRONES) or not np.allclose(shares.sum(1), 1.0) \
            or (shares < 0).any():
        raise ValueError(f"{name}.drone_shares() must be [{l}, {N_DRONES}] non-negative rows "
                         f"summing to 1, got shape {shares.shape}.")
    return shares


def _features(basis: nn.Module, states: np.ndarray) -> np.ndarray:
    """``basis`` on float64 states ``[..., 2, 4]`` -> float64 numpy ``[..., l]``."""
    with torch.no_grad():
        return basis(torch.from_numpy(np.array(states, dtype=np.float64))).cpu().numpy()


def joint_obs_from_states(states: Any) -> np.ndarray:
    """Joint observations of :class:`JointDroneEnv` from joint states.

    Drone ``i``'s observation is its own position and velocity, the other drone's, and
    its own door centre; the joint observation is drone 0's then drone 1's.

    Args:
        states: ``[..., 2, 4]`` positions and velocities (numpy or torch).

    Returns:
        ``[..., 20]`` float32, the inverse of :func:`joint_obs_to_state`.
    """
    s = states.detach().cpu().numpy() if isinstance(states, torch.Tensor) else np.asarray(states)
    if s.ndim < 2 or s.shape[-2:] != STATE_SHAPE:
        raise ValueError(f"states must have shape [..., 2, 4], got {list(s.shape)}.")
    doors = door_centres()
    parts = []
    for i in range(N_DRONES):
        door = np.broadcast_to(doors[i], (*s.shape[:-2], 2))
        parts.append(np.concatenate([s[..., i, :], s[..., 1 - i, :], door], -1))
    return np.concatenate(parts, -1).astype(np.float32)


def discounted_demo_feature_sums(demos: DroneDemonstrations, basis: nn.Module, gamma: float,
                                 *, absorbing: bool = True) -> torch.Tensor:
    """Per pair ``Σ_t γ^t φ(s_{t+1})`` over its ``lengths`` steps, as the solver counts them.

    With ``absorbing`` (the solver's default) the last state of each pair (both drones
    done) is absorbing: its term is ``γ^{L-1} φ(s_L) / (1 - γ)``.

    Args:
        demos: the demonstrations (``states [m, T+1, 2, 4]``, ``lengths [m]``).
        basis: a drone feature basis with ``l`` features.
        gamma: discount in ``(0, 1)``.
        absorbing: treat the final state as absorbing (see the module docstring).

    Returns:
        ``[m, l]`` float64.
    """
    gamma = _check_gamma(gamma)
    _basis_dim(basis, "basis")
    if not isinstance(demos, DroneDemonstrations):
        raise ValueError(f"demos must be DroneDemonstrations, got {type(demos).__name__}.")
    phi = torch.as_tensor(_features(basis, demos.states[:, 1:]))  # [m, T, l]
    T = phi.shape[1]
    lengths = torch.from_numpy(np.array(demos.lengths))
    t = torch.arange(T)
    w = gamma ** t.double() * (t < lengths[:, None])  # [m, T]
    if absorbing:
        last = (t == lengths[:, None] - 1)
        w = torch.where(last, w / (1.0 - gamma), w)
    return torch.einsum("mt,mtl->ml", w, phi)
