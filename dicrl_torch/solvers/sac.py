"""Entropy-regularised SAC-style constrained solver for the drone arena (DESIGN §5, §7).

The inner problem of D-ICRL needs, for ``η = [ω_r, λ]`` and ``ω_c``, the maximum causal
entropy (MCE) policy of the penalised linear reward

    r(s') = ω_r · φ_r(s') + λ · ω_c · φ_c(s'),

its discounted feature expectations ``μ_r(π) [l_r]`` and ``μ_c(π) [l_c]`` (hence
``J_ωc = ω_c · μ_c``), and the discounted log-likelihood of demonstrations under it.
In the continuous arena there is no exact solver; :class:`SACConstrainedSolver`
approximates the MCE policy with stable-baselines3 SAC on :class:`JointDroneEnv`
(both drones as one agent, action ``[4]``), and estimates the expectations from its own
rollouts.

Design choices, and why:

- **No stale rewards.** :class:`FeatureReplayBuffer` stores, per transition, the feature
  vectors ``φ_r(s') [l_r]``, ``φ_c(s') [l_c]`` (and the next state ``[2, 4]``), never a
  reward. :meth:`FeatureReplayBuffer.sample` computes the rewards from the weights set
  last by :meth:`FeatureReplayBuffer.set_weights`, so after ``η`` or ``ω_c`` change the
  whole buffer is relabelled at once and the old experience stays valid data.
- **Fixed temperature.** The MCE model is the soft-Bellman policy at temperature 1
  (``π ∝ exp(Q_soft)``, as the grid solver's ``temperature=1``), whose SAC form is the
  objective ``E Σ γ^t (r + α H(π(·|s_t)))`` with ``α = ent_coef = 1``. The temperature
  sets the reward scale that ``η`` is learned at, so it must not move: it is fixed
  (``ent_coef`` a float, no auto-tuning); ``"auto"`` is refused.
- **Warm start.** One SAC model and one buffer live as long as the solver;
  :meth:`SACConstrainedSolver.solve` relabels the buffer and *continues* training
  (``reset_num_timesteps=False``: no new warm-up of random actions, the episodes in
  flight go on), which is what makes thousands of inner iterations affordable.
- **Absorbing termination.** An episode of :class:`JointDroneEnv` ends when no drone
  flies (all arrived, or frozen in the true game). The grid world lets an expert stay at
  its goal, earning its features until the horizon; here the final state is treated as
  absorbing: the terminal transition earns ``φ(s_L) / (1 - γ)``, the discounted value of
  staying there forever. Without it, a positive reward for being near the door would
  teach the drones never to arrive (arriving ends the reward stream). Timeouts
  (``max_steps``) are truncations, bootstrapped by SB3 as usual. The same convention
  gives the rollout and the demonstration feature sums
  (:func:`discounted_demo_feature_sums`), so the two are comparable.
- **Features of the next state.** The reward of transition ``(s_t, a_t, s_{t+1})`` is
  that of ``s_{t+1}``, so the action is credited at once; the discounted sums are
  ``Σ_t γ^t φ(s_{t+1})`` (the initial state's features do not depend on the policy).
- **Private randomness.** SB3 draws from the global torch / numpy / ``random``
  generators (network init, buffer sampling, action sampling). The solver owns its
  own copies of those streams, seeded from ``seed``, and swaps them in only while SB3
  runs (:meth:`SACConstrainedSolver._private_rng`), restoring the caller's state
  afterwards: same seed, same numbers, and no global seeding seen from outside.
  Evaluation rollouts use an explicit ``torch.Generator`` and ``np.random.Generator``.
"""

from __future__ import annotations

import contextlib
import copy
import math
import random
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from stable_baselines3 import SAC
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.common.type_aliases import ReplayBufferSamples
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize
from torch import nn

from dicrl_torch.demos.drone_demos import DroneDemonstrations
from dicrl_torch.envs.drones import (
    N_DRONES,
    JointDroneEnv,
    door_centres,
    joint_obs_to_state,
)
from dicrl_torch.solvers.decomposed_sac import DecomposedSAC

__all__ = [
    "BoxScaler",
    "FeatureReplayBuffer",
    "SACConstrainedSolver",
    "SACLearnerModel",
    "SACSolution",
    "discounted_demo_feature_sums",
    "joint_obs_from_states",
]

STATE_SHAPE: tuple[int, int] = (N_DRONES, 4)


# --------------------------------------------------------------------------- helpers
def _is_int(x: Any) -> bool:
    return isinstance(x, int | np.integer) and not isinstance(x, bool)


def _check_gamma(gamma: Any) -> float:
    if isinstance(gamma, bool) or not isinstance(gamma, int | float | np.floating) \
            or not 0.0 < float(gamma) < 1.0:
        raise ValueError(f"gamma must be a float in (0, 1), got {gamma!r}.")
    return float(gamma)


def _weights(value: Any, name: str, dim: int) -> np.ndarray:
    """``value`` as a finite float64 ``[dim]`` array, or a ValueError naming it."""
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().numpy()
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(
            f"{name} must be a float vector of shape [{dim}], got {type(value).__name__}."
        ) from None
    if arr.shape != (dim,):
        raise ValueError(
            f"{name} must have shape [{dim}] (one weight per feature of its basis), got "
            f"{list(arr.shape)}."
        )
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf values: {arr.tolist()[:8]}...")
    return arr


def _check_fraction(value: Any, name: str) -> float:
    """A batch share in ``[0, 1)`` (some of each batch must be the policy's own)."""
    if isinstance(value, bool) or not isinstance(value, int | float | np.floating) \
            or not 0.0 <= float(value) < 1.0:
        raise ValueError(f"{name} must be a float in [0, 1), got {value!r}: the batch needs "
                         f"some of the policy's own transitions.")
    return float(value)


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


# ----------------------------------------------------------------------- the buffer
class FeatureReplayBuffer(ReplayBuffer):
    """SB3 replay buffer that stores features, not rewards, and relabels on sampling.

    Per transition it keeps, besides SB3's fields, ``next_states [2, 4]`` float64 (from
    ``info["state"]``, or the observation when absent), ``reward_features [l_r]`` and
    ``cost_features [l_c]`` of the next state, and ``reward_scale``: ``1 / (1 - γ)`` for
    a terminal transition when ``absorbing`` (see the module docstring), else 1. The
    reward SB3's ``add`` receives is ignored.

    :meth:`sample` returns rewards ``scale · (φ_r · ω_r + λ φ_c · ω_c)`` from the weights
    of the last :meth:`set_weights`, computed in float64 then cast to float32: ``[B, 1]``,
    or with ``per_drone`` ``[B, N_DRONES]``, each drone's share of that sum (the bases'
    ``drone_shares()``; the shared proximity split equally), for a per-drone critic. After
    :meth:`set_demonstrations`, a fixed share of every batch is drawn from the learner's
    own demonstrated transitions, relabelled the same way.

    Args:
        buffer_size, observation_space, action_space, device, n_envs,
            optimize_memory_usage, handle_timeout_termination: as SB3's ``ReplayBuffer``
            (``optimize_memory_usage`` is not supported).
        reward_basis: basis of ``φ_r`` (``l_r`` features).
        cost_basis: basis of ``φ_c`` (``l_c`` features).
        gamma: discount, for the absorbing terminal value.
        absorbing: treat terminal states as absorbing.
        feature_dtype: storage dtype of the features (float32 halves the memory of
            float64; indicator features are exact either way).
        per_drone: sample one reward column per drone (the bases must give
            ``drone_shares()``).
    """

    def __init__(
        self,
        buffer_size: int,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        device: torch.device | str = "auto",
        n_envs: int = 1,
        optimize_memory_usage: bool = False,
        handle_timeout_termination: bool = True,
        *,
        reward_basis: nn.Module,
        cost_basis: nn.Module,
        gamma: float,
        absorbing: bool = True,
        feature_dtype: Any = np.float32,
        per_drone: bool = False,
    ) -> None:
        if optimize_memory_usage:
            raise ValueError(
                "FeatureReplayBuffer does not support optimize_memory_usage=True (it keeps "
                "next observations per transition); pass optimize_memory_usage=False."
            )
        super().__init__(buffer_size, observation_space, action_space, device, n_envs,
                         False, handle_timeout_termination)
        self.reward_basis, self.cost_basis = reward_basis, cost_basis
        self.l_r = _basis_dim(reward_basis, "reward_basis")
        self.l_c = _basis_dim(cost_basis, "cost_basis")
        self.gamma = _check_gamma(gamma)
        self.absorbing = bool(absorbing)
        if not isinstance(per_drone, bool):
            raise ValueError(f"per_drone must be a bool, got {per_drone!r}.")
        # [l, G] share of each feature's reward per reward column (G = 1: the joint reward).
        self.shares: tuple[np.ndarray, np.ndarray] | None = None
        if per_drone:
            self.shares = (_drone_shares(reward_basis, "reward_basis"),
                           _drone_shares(cost_basis, "cost_basis"))
        self.n_rewards = N_DRONES if per_drone else 1
        shape = (self.buffer_size, self.n_envs)
        self.next_states = np.zeros((*shape, *STATE_SHAPE), dtype=np.float64)
        self.reward_features = np.zeros((*shape, self.l_r), dtype=feature_dtype)
        self.cost_features = np.zeros((*shape, self.l_c), dtype=feature_dtype)
        self.reward_scale = np.ones(shape, dtype=np.float64)
        self.reward_weights: np.ndarray | None = None
        self.multiplier: float | None = None
        self.cost_weights: np.ndarray | None = None
        self.last_sample_indices: tuple[np.ndarray, np.ndarray] | None = None
        """``(batch_inds, env_indices)`` of the last :meth:`sample`'s transitions from
        the env, for inspection."""
        self.demo_fraction = 0.0
        self._demo: dict[str, np.ndarray] | None = None

    def set_weights(self, reward_weights: Any, multiplier: Any, cost_weights: Any) -> None:
        """Set ``ω_r [l_r]``, ``λ`` and ``ω_c [l_c]``; every later sample uses them."""
        self.reward_weights = _weights(reward_weights, "reward_weights", self.l_r)
        try:
            lam = float(multiplier)  # also a 1-element array or tensor
        except (TypeError, ValueError):
            lam = float("nan")
        if not math.isfinite(lam):
            raise ValueError(f"multiplier (λ) must be a finite float, got {multiplier!r}.")
        self.multiplier = lam
        self.cost_weights = _weights(cost_weights, "cost_weights", self.l_c)

    def add(self, obs: np.ndarray, next_obs: np.ndarray, action: np.ndarray,
            reward: np.ndarray, done: np.ndarray, infos: list[dict[str, Any]]) -> None:
        """Store a step of all ``n_envs`` envs with the features of the next states."""
        # SB3 replaces next_obs of done envs by their terminal observation but leaves
        # infos alone: info["state"] is the (float64) state the step ended in.
        states = joint_obs_to_state(np.asarray(next_obs, dtype=np.float64))
        states = np.array(states)
        for i, info in enumerate(infos):
            if info.get("state") is not None:
                states[i] = info["state"]
        pos = self.pos
        self.next_states[pos] = states
        self.reward_features[pos] = _features(self.reward_basis, states)
        self.cost_features[pos] = _features(self.cost_basis, states)
        timeout = np.array([bool(info.get("TimeLimit.truncated", False)) for info in infos])
        terminal = np.asarray(done, dtype=bool).reshape(-1) & ~timeout
        self.reward_scale[pos] = np.where(terminal & self.absorbing,
                                          1.0 / (1.0 - self.gamma), 1.0)
        super().add(obs, next_obs, action, np.zeros_like(reward, dtype=np.float32), done, infos)

    def compute_rewards(self, batch_inds: np.ndarray, env_indices: np.ndarray) -> np.ndarray:
        """``[B]`` float64 (joint) rewards of stored transitions under the current weights."""
        return self._stored_rewards(batch_inds, env_indices).sum(-1)

    def _stored_rewards(self, batch_inds: np.ndarray, env_indices: np.ndarray) -> np.ndarray:
        """``[B, n_rewards]`` float64 rewards of stored transitions (see :meth:`_relabel`)."""
        return self._relabel(self.reward_features[batch_inds, env_indices],
                             self.cost_features[batch_inds, env_indices],
                             self.reward_scale[batch_inds, env_indices])

    def _relabel(self, phi_r: np.ndarray, phi_c: np.ndarray, scale: np.ndarray) -> np.ndarray:
        """``[B, n_rewards]`` float64 ``scale · (φ_r · ω_r + λ φ_c · ω_c)`` under the
        current weights, split into per-drone shares when ``per_drone``."""
        if self.reward_weights is None:
            raise RuntimeError(
                "FeatureReplayBuffer has no weights yet; call set_weights(reward_weights, "
                "multiplier, cost_weights) before sampling."
            )
        phi_r, phi_c = phi_r.astype(np.float64), phi_c.astype(np.float64)
        if self.shares is None:  # the joint reward exactly as before (no [l, 1] matmul)
            r = phi_r @ self.reward_weights + self.multiplier * (phi_c @ self.cost_weights)
            return (scale * r)[:, None]
        share_r, share_c = self.shares
        r = (phi_r @ (self.reward_weights[:, None] * share_r)
             + self.multiplier * (phi_c @ (self.cost_weights[:, None] * share_c)))
        return scale[:, None] * r

    def set_demonstrations(self, demos: DroneDemonstrations | None, fraction: float) -> None:
        """Mix demonstrated transitions into every batch (``None`` removes them).

        Each pair of length ``L`` gives ``L`` transitions ``(o_t, a_t, o_{t+1})``, the
        last one terminal (both drones done; absorbing when the buffer is), with the
        features of ``s_{t+1}``: the same record as an env transition, so the same
        relabelling applies. SAC is off-policy, so this leaves the soft-optimal policy
        it converges to unchanged; it shows the critic routes round the obstacles that
        its own exploration, starting from a policy that flies straight, rarely finds.

        Args:
            demos: the learner's own pairs (never another learner's).
            fraction: share of each batch drawn from them, in ``[0, 1)``.
        """
        fraction = _check_fraction(fraction, "fraction")
        if demos is None:
            self._demo, self.demo_fraction = None, 0.0
            return
        if not isinstance(demos, DroneDemonstrations):
            raise ValueError(f"demos must be DroneDemonstrations, got {type(demos).__name__}.")
        lengths = np.asarray(demos.lengths)
        pair = np.repeat(np.arange(demos.n_pairs), lengths)  # [n] transition -> pair
        t = np.concatenate([np.arange(n) for n in lengths])  # [n] its step in the pair
        states, next_states = demos.states[pair, t], demos.states[pair, t + 1]
        terminal = t == lengths[pair] - 1
        self._demo = {
            "obs": joint_obs_from_states(states),
            "next_obs": joint_obs_from_states(next_states),
            "actions": np.asarray(demos.actions[pair, t], dtype=np.float32).reshape(
                len(t), 2 * N_DRONES),
            "dones": terminal.astype(np.float32),
            "phi_r": _features(self.reward_basis, next_states),
            "phi_c": _features(self.cost_basis, next_states),
            "scale": np.where(terminal & self.absorbing, 1.0 / (1.0 - self.gamma), 1.0),
        }
        self.demo_fraction = fraction

    def sample(self, batch_size: int, env: VecNormalize | None = None) -> ReplayBufferSamples:
        """A batch of ``batch_size`` transitions: ``round(demo_fraction · batch_size)``
        demonstrated ones (if any) after those from the env."""
        n_demo = 0 if self._demo is None else int(round(batch_size * self.demo_fraction))
        online = super().sample(batch_size - n_demo, env=env)
        if n_demo == 0:
            return online
        d = self._demo
        idx = np.random.randint(0, len(d["dones"]), size=n_demo)  # noqa: NPY002 (as SB3)
        demo = self._samples(
            d["obs"][idx], d["actions"][idx], d["next_obs"][idx], d["dones"][idx],
            self._relabel(d["phi_r"][idx], d["phi_c"][idx], d["scale"][idx]), env)
        return ReplayBufferSamples(*(torch.cat(pair)
                                     for pair in zip(online[:5], demo[:5], strict=True)))

    def _samples(self, obs: np.ndarray, actions: np.ndarray, next_obs: np.ndarray,
                 dones: np.ndarray, rewards: np.ndarray,
                 env: VecNormalize | None) -> ReplayBufferSamples:
        """SB3's batch from ``[B, ...]`` arrays: normalised, float32 rewards
        ``[B, n_rewards]``."""
        data = (self._normalize_obs(obs, env), actions, self._normalize_obs(next_obs, env),
                dones.reshape(-1, 1),
                self._normalize_reward(rewards.astype(np.float32), env))
        return ReplayBufferSamples(*tuple(map(self.to_torch, data)))

    def _get_samples(self, batch_inds: np.ndarray,
                     env: VecNormalize | None = None) -> ReplayBufferSamples:
        # As SB3's ReplayBuffer._get_samples (global numpy stream for the env index, which
        # the solver makes private), with the rewards relabelled from the features.
        env_indices = np.random.randint(0, high=self.n_envs,  # noqa: NPY002 (as SB3)
                                        size=(len(batch_inds),))
        self.last_sample_indices = (np.asarray(batch_inds), env_indices)
        return self._samples(
            self.observations[batch_inds, env_indices, :],
            self.actions[batch_inds, env_indices, :],
            self.next_observations[batch_inds, env_indices, :],
            self.dones[batch_inds, env_indices] * (1 - self.timeouts[batch_inds, env_indices]),
            self._stored_rewards(batch_inds, env_indices), env)


# ----------------------------------------------------------------------- the result
def _mean_se(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean and standard error over dim 0 (SE is NaN with one sample)."""
    n = x.shape[0]
    mean = x.mean(0)
    if n < 2:
        return mean, torch.full_like(mean, float("nan"))
    return mean, x.std(0, correction=1) / math.sqrt(n)


@dataclass(frozen=True)
class SACSolution:
    """Rollout estimates of the current SAC policy (the grid solver's counterpart).

    Attributes:
        reward_sums: ``[n, l_r]`` float64 per-episode discounted ``Σ_t γ^t φ_r(s_{t+1})``.
        cost_sums: ``[n, l_c]`` float64, the same for ``φ_c``.
        lengths: ``[n]`` int64 episode lengths.
        reached: ``[n, 2]`` bool, drone reached its door in the episode.
        violated: ``[n, 2]`` bool, drone violated a true constraint in the episode.
        eta: ``[l_r + 1]`` float64 ``[ω_r, λ]`` the policy was trained for (or None).
        cost_weights: ``[l_c]`` float64 ``ω_c`` (or None).
        timesteps: env steps the SAC model had taken when evaluated.
        paths: per episode the drones' positions ``[L+1, 2, 2]`` (with
            ``evaluate(trajectories=True)``), else None.
    """

    reward_sums: torch.Tensor
    cost_sums: torch.Tensor
    lengths: torch.Tensor
    reached: torch.Tensor
    violated: torch.Tensor
    eta: torch.Tensor | None
    cost_weights: torch.Tensor | None
    timesteps: int
    solver: SACConstrainedSolver | None = field(default=None, repr=False, compare=False)
    paths: list[np.ndarray] | None = field(default=None, repr=False, compare=False)

    @property
    def n_episodes(self) -> int:
        return int(self.reward_sums.shape[0])

    @property
    def mu_r(self) -> torch.Tensor:
        """``[l_r]`` discounted reward-feature expectation ``μ_r(π)``."""
        return self.reward_sums.mean(0)

    @property
    def mu_r_se(self) -> torch.Tensor:
        """``[l_r]`` standard error of :attr:`mu_r`."""
        return _mean_se(self.reward_sums)[1]

    @property
    def mu_c(self) -> torch.Tensor:
        """``[l_c]`` discounted cost-feature expectation ``μ_c(π)``."""
        return self.cost_sums.mean(0)

    @property
    def mu_c_se(self) -> torch.Tensor:
        """``[l_c]`` standard error of :attr:`mu_c`."""
        return _mean_se(self.cost_sums)[1]

    def cost_value(self, cost_weights: Any = None) -> tuple[float, float]:
        """``J_ωc = ω_c · μ_c`` and its standard error over episodes.

        Args:
            cost_weights: ``[l_c]``; default the ``ω_c`` the policy was trained for.
        """
        w = self.cost_weights if cost_weights is None else cost_weights
        if w is None:
            raise ValueError("No cost_weights stored in this solution; pass cost_weights.")
        w = torch.as_tensor(_weights(w, "cost_weights", self.cost_sums.shape[1]))
        mean, se = _mean_se(self.cost_sums @ w)
        return float(mean), float(se)

    def penalised_return(self) -> tuple[float, float]:
        """The learned objective ``ω_r · μ_r + λ ω_c · μ_c`` under the weights the policy
        was trained for (the discounted return of its reward, without the entropy), and
        its standard error over episodes."""
        if self.eta is None or self.cost_weights is None:
            raise ValueError("This solution stores no (eta, cost_weights): it was not "
                             "trained for a reward; use solver.solve(...) first.")
        per = (self.reward_sums @ self.eta[:-1]
               + self.eta[-1] * (self.cost_sums @ self.cost_weights))  # [n]
        mean, se = _mean_se(per)
        return float(mean), float(se)

    def success_rate_under(self, constraints: Any) -> float:
        """SR in the game whose constraints are ``constraints`` (``[l_c]`` bool over the
        cost features, e.g. a learner's learned set): the fraction of drones that reached
        their door without accruing any of those features that are theirs (per
        ``drone_shares()``; a shared one, the proximity, counts for both). Computed from
        this solution's rollouts (the solver's game: nominal by default)."""
        if self.solver is None:
            raise ValueError("This solution has no solver (its cost basis is needed).")
        mask = torch.as_tensor(np.asarray(constraints, dtype=bool).reshape(-1))
        if mask.shape != (self.cost_sums.shape[1],):
            raise ValueError(f"constraints must be [{self.cost_sums.shape[1]}] bool, got "
                             f"shape {tuple(mask.shape)}.")
        owned = torch.as_tensor(_drone_shares(self.solver.cost_basis, "cost_basis") > 0)
        entered = (self.cost_sums > 0)[:, :, None] & (mask[:, None] & owned)[None]
        return float((self.reached & ~entered.any(1)).double().mean())

    @property
    def success_rate(self) -> float:
        """Fraction of drones that reached their door without a violation (SR)."""
        return float((self.reached & ~self.violated).double().mean())

    @property
    def violation_rate(self) -> float:
        """Mean over episodes of the fraction of drones that violated (CVR)."""
        return float(self.violated.double().mean())

    def feature_expectation(self, features: Any) -> torch.Tensor:
        """``[l]`` discounted expectation of ``features``: the solver's reward or cost
        basis (the object itself, like the grid solver's accessor) or ``"reward"`` /
        ``"cost"``."""
        name = features if isinstance(features, str) else None
        if name == "reward" or (self.solver is not None
                                and features is self.solver.reward_basis):
            return self.mu_r
        if name == "cost" or (self.solver is not None and features is self.solver.cost_basis):
            return self.mu_c
        raise ValueError(
            f"feature_expectation takes the solver's reward_basis or cost_basis (or "
            f"'reward' / 'cost'), got {type(features).__name__}; other bases are not "
            f"recorded in the rollouts."
        )


# ----------------------------------------------------------------------- the solver
# SB3 draws from the legacy global generators; these swap them (NPY002 is intended).
def _capture_rng(cuda: bool) -> tuple[Any, ...]:
    return (torch.get_rng_state(), torch.cuda.get_rng_state_all() if cuda else None,
            np.random.get_state(), random.getstate())  # noqa: NPY002


def _restore_rng(state: tuple[Any, ...], cuda: bool) -> None:
    torch.set_rng_state(state[0])
    if cuda:
        torch.cuda.set_rng_state_all(state[1])
    np.random.set_state(state[2])  # noqa: NPY002
    random.setstate(state[3])


class SACConstrainedSolver:
    """Entropy-regularised SAC on ``r = ω_r·φ_r + λ ω_c·φ_c``, warm-started across calls.

    Example::

        solver = SACConstrainedSolver(reward_basis=DoorLocationRewardBasis(),
                                      cost_basis=CellOccupancyCostBasis(), seed=0)
        sol = solver.solve(eta, cost_weights, timesteps=20_000)  # eta = [ω_r, λ]
        grad = torch.cat([sol.mu_r - mu_hat, ...]); ll = solver.log_likelihood(demos)

    Args:
        reward_basis: drone basis of ``φ_r`` (``l_r`` features), e.g.
            :class:`~dicrl_torch.features.drone.DoorLocationRewardBasis`.
        cost_basis: drone basis of ``φ_c`` (``l_c``), e.g. ``CellOccupancyCostBasis``.
        seed: the solver's only source of randomness (networks, env starts and noise,
            buffer sampling, exploration, evaluation).
        n_envs: parallel envs of the ``DummyVecEnv`` that SAC collects from.
        device: ``"cpu"``, ``"cuda"`` or a ``torch.device`` for the networks.
        gamma: discount.
        ent_coef: the fixed entropy temperature ``α`` (1.0: the MCE model at the scale of
            ``η``; see the module docstring). Must be a positive number.
        absorbing: treat terminal states as absorbing (module docstring).
        n_eval_episodes: rollouts per :meth:`evaluate` (default of :meth:`solve`).
        env_kwargs: forwarded to :class:`JointDroneEnv` / ``DroneArena``; the default
            game is the *nominal* one (``constrained=False``): the learner knows the
            nominal dynamics, not the constraints.
        learning_rate, buffer_size, batch_size, learning_starts, tau, train_freq,
            gradient_steps: SAC's (``buffer_size`` counts transitions over all envs).
        net_arch: hidden layers of actor and critics.
        action_margin: demonstrated actions are clipped to ``±(1 - action_margin)`` in
            :meth:`log_likelihood` (the squashed density is infinite at ``±1``).
        feature_dtype: storage dtype of the buffer's features.
        demo_fraction: share of each SAC batch drawn from the demonstrations given to
            :meth:`set_demonstrations` (none are by default), in ``[0, 1)``.
        scale_observations: feed actor and critics observations mapped onto ``[-1, 1]``
            by the observation space's bounds (:class:`BoxScaler`).
        per_drone_critics: critics with one soft-Q column per drone, each trained on that
            drone's share of the reward (:mod:`~dicrl_torch.solvers.decomposed_sac`; the
            fixed point is plain SAC's).
        sac_kwargs: further keyword arguments for ``stable_baselines3.SAC``.
    """

    def __init__(
        self,
        *,
        reward_basis: nn.Module,
        cost_basis: nn.Module,
        seed: int,
        n_envs: int = 1,
        device: str | torch.device = "cpu",
        gamma: float = 0.99,
        ent_coef: float = 1.0,
        absorbing: bool = True,
        n_eval_episodes: int = 10,
        env_kwargs: dict[str, Any] | None = None,
        learning_rate: float = 3e-4,
        buffer_size: int = 100_000,
        batch_size: int = 256,
        learning_starts: int = 1_000,
        tau: float = 0.005,
        train_freq: int = 1,
        gradient_steps: int = 1,
        net_arch: Sequence[int] = (64, 64),
        action_margin: float = 1e-3,
        feature_dtype: Any = np.float32,
        demo_fraction: float = 0.0,
        scale_observations: bool = False,
        per_drone_critics: bool = False,
        sac_kwargs: dict[str, Any] | None = None,
    ) -> None:
        self.demo_fraction = _check_fraction(demo_fraction, "demo_fraction")
        self.l_r = _basis_dim(reward_basis, "reward_basis")
        self.l_c = _basis_dim(cost_basis, "cost_basis")
        self.reward_basis, self.cost_basis = reward_basis, cost_basis
        if not _is_int(seed):
            raise ValueError(f"seed must be an int (the solver's only randomness), got {seed!r}.")
        if not _is_int(n_envs) or n_envs < 1:
            raise ValueError(f"n_envs must be a positive int, got {n_envs!r}.")
        if isinstance(ent_coef, str) or isinstance(ent_coef, bool) \
                or not isinstance(ent_coef, int | float | np.floating) \
                or not math.isfinite(ent_coef) or ent_coef <= 0:
            raise ValueError(
                f"ent_coef must be a fixed positive number (the MCE temperature, 1.0 at the "
                f"scale of η), got {ent_coef!r}; automatic tuning ('auto') would change the "
                f"model the rewards are learned for."
            )
        if not _is_int(n_eval_episodes) or n_eval_episodes < 1:
            raise ValueError(f"n_eval_episodes must be a positive int, got {n_eval_episodes!r}.")
        if isinstance(action_margin, bool) or not isinstance(action_margin, int | float) \
                or not 0.0 < action_margin < 1.0:
            raise ValueError(f"action_margin must be a float in (0, 1), got {action_margin!r}.")
        self.seed = int(seed)
        self.n_envs = int(n_envs)
        self.device = torch.device(device)
        if self.device.type == "cuda" and not torch.cuda.is_available():
            raise ValueError(f"device={device!r} but CUDA is not available; use device='cpu'.")
        self.gamma = _check_gamma(gamma)
        self.ent_coef = float(ent_coef)
        self.absorbing = bool(absorbing)
        self.n_eval_episodes = int(n_eval_episodes)
        self.action_margin = float(action_margin)
        self.env_kwargs = {"constrained": False, **(env_kwargs or {})}
        if "reward_fn" in self.env_kwargs:
            raise ValueError(
                "env_kwargs must not set reward_fn: the solver's buffer computes rewards "
                "from features; drop the reward_fn key."
            )
        # Validate the env kwargs now, with a clear error, rather than inside SB3.
        probe = JointDroneEnv(**self.env_kwargs)
        self._obs_low, self._obs_high = probe.observation_space.low, probe.observation_space.high
        probe.close()

        self._rng_state: tuple[Any, ...] | None = None
        self._eval_rng = np.random.default_rng([self.seed, 1])
        self._eval_gen = torch.Generator(device=self.device)
        self._eval_gen.manual_seed(int(np.random.default_rng([self.seed, 2]).integers(2**62)))
        self._eval_envs: dict[bool, list[JointDroneEnv]] = {False: [], True: []}

        kwargs = dict(sac_kwargs or {})
        for key in ("ent_coef", "replay_buffer_class", "seed", "gamma"):
            if key in kwargs:
                raise ValueError(
                    f"sac_kwargs must not set {key!r}: the solver fixes it; use the solver's "
                    f"own argument instead."
                )
        if not isinstance(scale_observations, bool):
            raise ValueError(f"scale_observations must be a bool, got {scale_observations!r}.")
        self.scale_observations = scale_observations
        policy_kwargs = {"net_arch": list(net_arch), **kwargs.pop("policy_kwargs", {})}
        if scale_observations:
            if "features_extractor_class" in policy_kwargs:
                raise ValueError("scale_observations=True sets the features extractor; drop "
                                 "features_extractor_class from sac_kwargs['policy_kwargs'].")
            policy_kwargs["features_extractor_class"] = BoxScaler
        if not isinstance(per_drone_critics, bool):
            raise ValueError(f"per_drone_critics must be a bool, got {per_drone_critics!r}.")
        self.per_drone_critics = per_drone_critics
        algorithm = SAC
        if per_drone_critics:
            algorithm = DecomposedSAC
            policy_kwargs["n_rewards"] = N_DRONES
        # Even building the vec env draws from the global numpy stream (SB3): all of it
        # happens on the solver's private streams.
        with self._private_rng():
            self.vec_env = make_vec_env(JointDroneEnv, n_envs=self.n_envs,
                                        env_kwargs=self.env_kwargs, vec_env_cls=DummyVecEnv)
            self.vec_env.seed(self.seed)  # used at the first reset, inside learn()
            self.model = algorithm(
                "MlpPolicy", self.vec_env, learning_rate=learning_rate,
                buffer_size=buffer_size, learning_starts=learning_starts,
                batch_size=batch_size, tau=tau, gamma=self.gamma, train_freq=train_freq,
                gradient_steps=gradient_steps, ent_coef=self.ent_coef,
                replay_buffer_class=FeatureReplayBuffer,
                replay_buffer_kwargs={"reward_basis": reward_basis, "cost_basis": cost_basis,
                                      "gamma": self.gamma, "absorbing": self.absorbing,
                                      "feature_dtype": feature_dtype,
                                      "per_drone": per_drone_critics},
                policy_kwargs=policy_kwargs, device=self.device, seed=None, verbose=0,
                **kwargs,
            )
        # Without a logger of its own, every learn() call makes SB3 create an empty
        # SB3-<time> directory in the system temp dir: thousands per table2 run.
        self.model.set_logger(Logger(folder=None, output_formats=[]))
        # Random warm-up actions come from the action space's own generator.
        self.model.action_space.seed(self.seed)
        self.eta: np.ndarray | None = None
        self.cost_weights: np.ndarray | None = None
        self.last_checks: list[dict[str, Any]] = []
        """Per chunk of the last :meth:`solve_keeping_best`: its scores."""

    # ---- randomness ---------------------------------------------------------------
    @contextlib.contextmanager
    def _private_rng(self) -> Iterator[None]:
        """Run SB3 on the solver's own global-RNG streams; restore the caller's after."""
        cuda = self.device.type == "cuda"
        caller = _capture_rng(cuda)
        try:
            if self._rng_state is None:
                torch.manual_seed(self.seed)
                np.random.seed(self.seed % 2**32)  # noqa: NPY002 (private, restored)
                random.seed(self.seed)
            else:
                _restore_rng(self._rng_state, cuda)
            yield
        finally:
            self._rng_state = _capture_rng(cuda)
            _restore_rng(caller, cuda)

    def clone(self, seed: int) -> SACConstrainedSolver:
        """A copy of this solver — networks, optimisers, replay buffer, envs — with its
        own random streams seeded from ``seed``: learners warm-started from one shared
        pre-trained policy, as all start from the same ``η(0)``, then diverge."""
        if not _is_int(seed):
            raise ValueError(f"seed must be an int, got {seed!r}.")
        twin = copy.deepcopy(self)
        twin.seed = int(seed)
        twin._rng_state = None  # fresh private streams from the new seed at next use
        twin._eval_rng = np.random.default_rng([twin.seed, 1])
        twin._eval_gen.manual_seed(int(np.random.default_rng([twin.seed, 2]).integers(2**62)))
        twin.model.action_space.seed(twin.seed)
        # The episodes in flight go on, on streams of their own (not the original's).
        for k, env in enumerate(twin.vec_env.envs):
            env.unwrapped.arena._rng = np.random.default_rng([twin.seed, 3, k])
        return twin

    # ---- accessors ----------------------------------------------------------------
    @property
    def replay_buffer(self) -> FeatureReplayBuffer:
        return self.model.replay_buffer

    @property
    def num_timesteps(self) -> int:
        """Env steps taken so far (over all envs)."""
        return int(self.model.num_timesteps)

    def set_weights(self, eta: Any, cost_weights: Any) -> None:
        """Set ``η = [ω_r, λ]`` (``[l_r + 1]``) and ``ω_c`` (``[l_c]``) for training."""
        eta = _weights(eta, "eta", self.l_r + 1)
        cost_weights = _weights(cost_weights, "cost_weights", self.l_c)
        self.replay_buffer.set_weights(eta[:-1], eta[-1], cost_weights)
        self.eta, self.cost_weights = eta, cost_weights

    def set_demonstrations(self, demos: DroneDemonstrations | None) -> None:
        """Let ``demo_fraction`` of every SAC batch come from ``demos``' transitions,
        relabelled with the current weights like the rest (see
        :meth:`FeatureReplayBuffer.set_demonstrations`). Give a learner only its own
        pairs; ``None`` removes them."""
        self.replay_buffer.set_demonstrations(demos, self.demo_fraction)

    # ---- solving ------------------------------------------------------------------
    def solve(self, eta: Any, cost_weights: Any, timesteps: int, *,
              n_eval_episodes: int | None = None) -> SACSolution:
        """Continue training on the reward of ``(η, ω_c)``, then evaluate.

        Args:
            eta: ``[l_r + 1]`` ``[ω_r, λ]``.
            cost_weights: ``[l_c]`` ``ω_c``.
            timesteps: further env steps (over all envs); 0 only evaluates.
            n_eval_episodes: rollouts for the estimates (default the solver's).

        Returns:
            The :class:`SACSolution` of the policy after training.
        """
        self._train(eta, cost_weights, timesteps)
        return self.evaluate(n_eval_episodes)

    def solve_keeping_best(self, eta: Any, cost_weights: Any, timesteps: int, *, checks: int,
                           restarts: int = 1, n_eval_episodes: int | None = None,
                           deterministic: bool = False, constraints: Any = None) -> SACSolution:
        """Train ``timesteps`` in ``checks`` near-equal chunks and end with the networks
        whose policy scored the highest learned objective
        (:meth:`SACSolution.penalised_return`) after any chunk; with ``constraints``, the
        highest :meth:`SACSolution.success_rate_under` them first (ties: the objective).

        SAC's iterates can swing between behaviours from one chunk to the next (README,
        "Drones"); this keeps the best one seen, as an evaluation callback that saves the
        best model does. With ``restarts`` > 1 the same is done from this solver's current
        state by ``restarts - 1`` clones as well (:meth:`clone`, seeds drawn from this
        solver's), whose lineages diverge, and the best chunk of any of them is kept: more
        independent chances when one lineage never settles. The score is the learner's
        own: its ``(η, ω_c)``, rolled out in the solver's game (the nominal one by default);
        no true constraint is consulted.

        Args:
            eta, cost_weights, n_eval_episodes: as :meth:`solve` (rollouts per score).
            timesteps: env steps per restart (>= ``checks``).
            checks: number of chunks per restart, each followed by a score; 1 (with one
                restart) is :meth:`solve`.
            restarts: independent continuations from the current state (1: this solver's).
            deterministic: score the mean-action policy (how it is deployed).
            constraints: ``[l_c]`` bool, the learner's constraint set (e.g. its
                ``ω_c ≥ 0.5``), or None.

        Returns:
            The best chunk's :class:`SACSolution` (its rollouts gave the score); this
            solver's networks are left as that chunk's. Every chunk's ``{"restart",
            "timesteps", "penalised_return", "success_under_constraints"}`` (the last None
            without ``constraints``) is left in ``self.last_checks``.
        """
        if not _is_int(checks) or checks < 1:
            raise ValueError(f"checks must be a positive int, got {checks!r}.")
        if not _is_int(timesteps) or timesteps < checks:
            raise ValueError(f"timesteps must be an int >= checks={checks}, got "
                             f"{timesteps!r}.")
        if not _is_int(restarts) or restarts < 1:
            raise ValueError(f"restarts must be a positive int, got {restarts!r}.")
        chunks = np.diff(np.linspace(0, int(timesteps), checks + 1).round().astype(int))
        # Clone seeds come from this solver's seed, so a run is reproducible. The clones
        # run first, one at a time (each holds a copy of the replay buffer), while this
        # solver still has the state they start from; it runs last as restart 0.
        seeds = np.random.SeedSequence([self.seed, 4]).generate_state(restarts - 1)
        order = [*range(1, restarts), 0]
        best, best_key, best_state = None, None, None
        self.last_checks = []
        for r in order:
            solver = self if r == 0 else self.clone(int(seeds[r - 1]))
            for k, steps in enumerate(chunks):
                solver._train(eta, cost_weights, int(steps))
                solution = solver.evaluate(n_eval_episodes, deterministic=deterministic)
                objective = solution.penalised_return()[0]
                success = (None if constraints is None
                           else solution.success_rate_under(constraints))
                self.last_checks.append({"restart": r, "timesteps": solver.num_timesteps,
                                         "penalised_return": objective,
                                         "success_under_constraints": success})
                # Ties go to the earlier restart, then the earlier chunk.
                key = (0.0 if success is None else success, objective, -r, -k)
                if best is None or key > best_key:
                    best, best_key = solution, key
                    best_state = copy.deepcopy(solver.model.policy.state_dict())
            if solver is not self:
                solver.close()
        self.last_checks.sort(key=lambda c: c["restart"])  # stable: chunks stay in order
        self.model.policy.load_state_dict(best_state)
        # A clone's solution: its policy now lives here (the clone is closed).
        return replace(best, solver=self)

    def _train(self, eta: Any, cost_weights: Any, timesteps: int) -> None:
        """Set the weights (relabelling the buffer) and continue SAC for ``timesteps``."""
        if not _is_int(timesteps) or timesteps < 0:
            raise ValueError(f"timesteps must be an int >= 0, got {timesteps!r}.")
        self.set_weights(eta, cost_weights)
        if timesteps > 0:
            with self._private_rng():
                self.model.learn(total_timesteps=int(timesteps), reset_num_timesteps=False)

    def _policy_params(self, obs: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and log-std ``[B, 4]`` (pre-squash) of the actor at observations."""
        actor = self.model.actor
        with torch.no_grad():
            o = torch.as_tensor(obs, dtype=torch.float32, device=self.device)
            mean, log_std, _ = actor.get_action_dist_params(o)
        return mean, log_std

    def act(self, obs: np.ndarray, deterministic: bool = False) -> np.ndarray:
        """Actions ``[B, 4]`` in ``[-1, 1]`` for joint observations ``[B, 20]``, sampled with
        the solver's evaluation generator (tanh of the mean when ``deterministic``)."""
        mean, log_std = self._policy_params(obs)
        if deterministic:
            return torch.tanh(mean).cpu().numpy()
        eps = torch.randn(mean.shape, generator=self._eval_gen, device=self.device)
        return torch.tanh(mean + log_std.exp() * eps).cpu().numpy()

    def evaluate(self, n_episodes: int | None = None, *, deterministic: bool = False,
                 true_game: bool = False, rng: np.random.Generator | None = None,
                 trajectories: bool = False) -> SACSolution:
        """Roll out the current policy for ``n_episodes`` episodes and estimate the
        discounted feature sums (absorbing terminal, as in training).

        Episodes are stepped in lock-step so the actor runs once per step on a batch.

        Args:
            n_episodes: rollouts (default the solver's ``n_eval_episodes``).
            deterministic: act with ``tanh`` of the mean.
            true_game: roll out in the game with the TRUE constraints (violators freeze:
                the metrics SR and CVR), not the solver's nominal game.
            rng: draws the episodes' env seeds (default the solver's own evaluation
                stream); pass a fresh seeded generator to compare policies on common
                random numbers.
            trajectories: also keep the positions ``[n, L+1, 2, 2]`` (for figures).
        """
        n = self.n_eval_episodes if n_episodes is None else n_episodes
        if not _is_int(n) or n < 1:
            raise ValueError(f"n_episodes must be a positive int, got {n!r}.")
        cache = self._eval_envs[bool(true_game)]
        kwargs = {**self.env_kwargs, "constrained": True} if true_game else self.env_kwargs
        while len(cache) < n:
            cache.append(JointDroneEnv(**kwargs))
        envs = cache[:n]
        seeds = (self._eval_rng if rng is None else rng).integers(0, 2**31 - 1, size=n)
        obs = np.stack([env.reset(seed=int(s))[0] for env, s in zip(envs, seeds, strict=True)])
        sums_r, sums_c = np.zeros((n, self.l_r)), np.zeros((n, self.l_c))
        lengths = np.zeros(n, dtype=np.int64)
        reached = np.zeros((n, N_DRONES), dtype=bool)
        violated = np.zeros((n, N_DRONES), dtype=bool)
        disc = np.ones(n)
        alive = np.ones(n, dtype=bool)
        bonus = 1.0 / (1.0 - self.gamma) if self.absorbing else 1.0
        paths = [[joint_obs_to_state(o)[:, :2]] for o in obs] if trajectories else None
        while alive.any():
            idx = np.flatnonzero(alive)
            actions = self.act(obs[idx], deterministic)
            states = np.zeros((len(idx), *STATE_SHAPE))
            terminal = np.zeros(len(idx), dtype=bool)
            for j, i in enumerate(idx):
                o, _, term, trunc, info = envs[i].step(actions[j])
                obs[i], states[j], terminal[j] = o, info["state"], term
                reached[i] |= info["reached"]
                violated[i] |= info["violated"]
                lengths[i] += 1
                if paths is not None:
                    paths[i].append(np.array(info["state"])[:, :2])
                if term or trunc:
                    alive[i] = False
            w = disc[idx] * np.where(terminal, bonus, 1.0)
            sums_r[idx] += w[:, None] * _features(self.reward_basis, states)
            sums_c[idx] += w[:, None] * _features(self.cost_basis, states)
            disc[idx] *= self.gamma
        return SACSolution(
            reward_sums=torch.from_numpy(sums_r), cost_sums=torch.from_numpy(sums_c),
            lengths=torch.from_numpy(lengths), reached=torch.from_numpy(reached),
            violated=torch.from_numpy(violated),
            eta=None if self.eta is None else torch.from_numpy(self.eta.copy()),
            cost_weights=None if self.cost_weights is None
            else torch.from_numpy(self.cost_weights.copy()),
            timesteps=self.num_timesteps, solver=self,
            paths=None if paths is None else [np.stack(p) for p in paths],
        )

    # ---- likelihood ---------------------------------------------------------------
    def log_likelihood(self, demos: DroneDemonstrations, *,
                       per_pair: bool = False) -> float | torch.Tensor:
        """Discounted log-likelihood ``Σ_pairs Σ_t γ^t ln π(a_t | s_t)`` of demonstrations.

        ``π`` is the SAC policy's squashed Gaussian density on ``[-1, 1]^4``: per action
        dimension ``ln N(atanh a; μ, σ) − ln(1 − a²)``. A drone's dimensions count only
        while it flies (``t < demos.drone_lengths()``): its later commands are ignored by
        the env, and as the dimensions are independent, dropping them is the exact
        marginal. Actions are clipped to ``±(1 − action_margin)``.

        Args:
            demos: the demonstrations.
            per_pair: return the ``[m]`` float64 per-pair values instead of their sum.

        Returns:
            The sum over pairs (float), or ``[m]`` with ``per_pair``.
        """
        if not isinstance(demos, DroneDemonstrations):
            raise ValueError(f"demos must be DroneDemonstrations, got {type(demos).__name__}.")
        m, T = demos.n_pairs, demos.horizon
        obs = np.clip(joint_obs_from_states(demos.states[:, :T]), self._obs_low, self._obs_high)
        mean, log_std = self._policy_params(obs.reshape(m * T, -1))
        mean, log_std = mean.double().cpu(), log_std.double().cpu()
        bound = 1.0 - self.action_margin
        a = torch.from_numpy(np.array(demos.actions).reshape(m * T, 2 * N_DRONES))
        a = a.clamp(-bound, bound)
        u = torch.atanh(a)
        logp = (torch.distributions.Normal(mean, log_std.exp()).log_prob(u)
                - torch.log1p(-a * a))  # [m*T, 4]
        logp = logp.reshape(m, T, N_DRONES, 2).sum(-1)  # [m, T, 2] per drone
        flying = torch.arange(T)[None, :, None] < torch.as_tensor(
            demos.drone_lengths())[:, None, :]  # [m, T, 2]
        disc = self.gamma ** torch.arange(T, dtype=torch.float64)
        per = (torch.where(flying, logp, 0.0).sum(-1) * disc).sum(1)  # [m]
        return per if per_pair else float(per.sum())

    def close(self) -> None:
        """Close the training and evaluation envs."""
        self.vec_env.close()
        for env in self._eval_envs[False] + self._eval_envs[True]:
            env.close()


# ----------------------------------------------------------------------- D-ICRL's model
class SACLearnerModel:
    """The drone learners' model for the D-ICRL trainer (:mod:`dicrl_torch.algos.models`).

    Each local learner owns one :class:`SACConstrainedSolver`: SAC is warm-started across
    calls, so a solver's state is that learner's policy. Every :meth:`solve` continues
    training for ``timesteps`` env steps on the new ``(η, ω_c)`` and then estimates
    ``μ_r``, ``μ_c`` from ``n_eval_episodes`` rollouts; the estimates are noisy, which the
    trainer's diminishing steps average out.

    Args:
        solvers: one solver per local learner (same bases, discount and game).
        timesteps: env steps of SAC training per solve (per inner step).
        n_eval_episodes: rollouts per estimate (default each solver's own).
    """

    def __init__(self, *, solvers: Sequence[SACConstrainedSolver], timesteps: int,
                 n_eval_episodes: int | None = None) -> None:
        solvers = list(solvers)
        if not solvers or not all(isinstance(s, SACConstrainedSolver) for s in solvers):
            raise ValueError("solvers must be a non-empty list of SACConstrainedSolver, one "
                             "per local learner.")
        first = solvers[0]
        for s in solvers[1:]:
            if (s.l_r, s.l_c, s.gamma, s.absorbing) != (first.l_r, first.l_c, first.gamma,
                                                         first.absorbing):
                raise ValueError("All learners' solvers must share the feature bases' "
                                 "widths, gamma and the absorbing convention.")
        if not _is_int(timesteps) or timesteps < 0:
            raise ValueError(f"timesteps must be an int >= 0, got {timesteps!r}.")
        if n_eval_episodes is not None and (not _is_int(n_eval_episodes)
                                            or n_eval_episodes < 1):
            raise ValueError(f"n_eval_episodes must be a positive int, got {n_eval_episodes!r}.")
        self.solvers, self.timesteps, self.n_eval_episodes = solvers, int(timesteps), \
            n_eval_episodes
        self.reward_dim, self.cost_dim = first.l_r, first.l_c
        self.dtype = None

    def _solver(self, learner: int) -> SACConstrainedSolver:
        if not 0 <= learner < len(self.solvers):
            raise ValueError(f"learner {learner} has no solver: this model holds "
                             f"{len(self.solvers)}; give one solver per local learner.")
        return self.solvers[learner]

    def statistics(self, demos: DroneDemonstrations):
        """``μ̂_r``, the cost accrual and ``m`` of a learner's pairs, counted as the
        solver counts its rollouts (next-state features, absorbing end)."""
        from dicrl_torch.algos.icrl import LocalStatistics

        s = self.solvers[0]
        if not isinstance(demos, DroneDemonstrations) or demos.n_pairs < 1:
            raise ValueError("A drone learner needs DroneDemonstrations with at least one "
                             "pair.")

        def mean(basis: nn.Module) -> torch.Tensor:
            return discounted_demo_feature_sums(demos, basis, s.gamma,
                                                absorbing=s.absorbing).mean(0)

        return LocalStatistics(m=demos.n_pairs, mu_r_hat=mean(s.reward_basis),
                               cost_accrual=mean(s.cost_basis))

    def solve(self, learner: int, eta: torch.Tensor, cost_weights: torch.Tensor
              ) -> SACSolution:
        return self._solver(learner).solve(eta, cost_weights, self.timesteps,
                                           n_eval_episodes=self.n_eval_episodes)

    def log_likelihood(self, learner: int, eta: torch.Tensor, cost_weights: torch.Tensor,
                       demos: DroneDemonstrations) -> float:
        """Trains on ``(η, ω_c)`` for ``timesteps`` first (the policy IS the solver's
        state), then scores ``demos`` under it."""
        solver = self._solver(learner)
        solver.solve(eta, cost_weights, self.timesteps, n_eval_episodes=1)
        return solver.log_likelihood(demos)

    def describe(self) -> str:
        s = self.solvers[0]
        return (f"SAC x{len(self.solvers)} steps={self.timesteps} gamma={s.gamma} "
                f"ent={s.ent_coef} absorbing={s.absorbing}")
