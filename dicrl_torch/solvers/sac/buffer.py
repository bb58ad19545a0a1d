"""The SAC solver's replay buffer: features stored, rewards relabelled on sampling.

See :mod:`dicrl_torch.solvers.sac` ("No stale rewards", "Absorbing termination").
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.type_aliases import ReplayBufferSamples
from stable_baselines3.common.vec_env import VecNormalize
from torch import nn

from dicrl_torch.solvers.sac.checks import _check_fraction, _check_gamma, _weights
from dicrl_torch.solvers.sac.features import _agent_shares, _basis_dim, _features
from dicrl_torch.solvers.sac.protocol import as_continuous, step_fields
from dicrl_torch.solvers.sac.state import (
    array_of,
    check_optional_array,
    check_tensor,
    optional_array,
    optional_tensor,
    tensor_of,
    torch_dtype,
)

__all__ = ["FeatureReplayBuffer"]


class FeatureReplayBuffer(ReplayBuffer):
    """SB3 replay buffer that stores features, not rewards, and relabels on sampling.

    Per transition it keeps, besides SB3's fields, ``next_states [N, d_s]`` float64 (the
    step's ``info["state"]``), ``reward_features [l_r]`` and ``cost_features [l_c]`` of
    the next state, and ``reward_scale``: ``1 / (1 - γ)`` for a terminal transition when
    ``absorbing`` (see the package docstring), else 1. The reward SB3's ``add`` receives
    is ignored.

    :meth:`sample` returns rewards ``scale · (φ_r · ω_r + λ φ_c · ω_c)`` from the weights
    of the last :meth:`set_weights`, computed in float64 then cast to float32: ``[B, 1]``,
    or with ``per_agent`` ``[B, N]``, each agent's share of that sum (the bases'
    ``agent_shares()``; a shared feature split equally), for a per-agent critic. After
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
        state_shape: ``(N, d_s)`` of the joint states in the env's infos.
        per_agent: sample one reward column per agent (the bases must give
            ``agent_shares()``).
        split_cost: sample the reward part ``ω_r·φ_r`` and the cost part
            ``λ ω_c·φ_c`` as separate columns (after the agents' ones when
            ``per_agent``: ``[B, 2 G]``); their sum is the reward either way.
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
        state_shape: tuple[int, int],
        per_agent: bool = False,
        split_cost: bool = False,
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
        if not isinstance(per_agent, bool):
            raise ValueError(f"per_agent must be a bool, got {per_agent!r}.")
        self.state_shape = tuple(int(d) for d in state_shape)
        n_agents = self.state_shape[0]
        # [l, G] share of each feature's reward per reward column (G = 1: the joint reward).
        self.shares: tuple[np.ndarray, np.ndarray] | None = None
        if per_agent:
            self.shares = (_agent_shares(reward_basis, "reward_basis", n_agents),
                           _agent_shares(cost_basis, "cost_basis", n_agents))
        if not isinstance(split_cost, bool):
            raise ValueError(f"split_cost must be a bool, got {split_cost!r}.")
        self.split_cost = split_cost
        self.n_rewards = (n_agents if per_agent else 1) * (2 if split_cost else 1)
        shape = (self.buffer_size, self.n_envs)
        self.next_states = np.zeros((*shape, *self.state_shape), dtype=np.float64)
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
        self._demo_returns: np.ndarray | None = None  # under the current weights
        self.last_demo_indices: np.ndarray | None = None
        """``[n_demo]``: the demonstrated transitions of the last :meth:`sample`'s last
        rows (None without any); their returns are computed only when asked for."""
        self.penalty_basis: nn.Module | None = None
        """Set by :meth:`set_penalty_basis`: the basis of the penalty's features, computed
        from the stored next states at sampling (None: the stored ``φ_c``)."""

    def set_penalty_basis(self, basis: nn.Module | None) -> None:
        """Relabel the penalty ``λ ω_c · φ`` with ``φ = basis(next state)`` instead of the
        stored ``φ_c`` (``l_c`` features, e.g. a cost basis grown by a margin), for every
        transition, stored or demonstrated, until set back to None."""
        if basis is not None:
            if _basis_dim(basis, "penalty_basis") != self.l_c:
                raise ValueError(f"penalty_basis has {basis.dim} features, the cost basis "
                                 f"{self.l_c}; give the cost basis grown by a margin.")
            if self._demo is not None and self._demo.get("next_states") is None:
                raise ValueError(
                    "The demonstrations in this buffer came from a state saved without their "
                    "next states; call set_demonstrations again before set_penalty_basis.")
        self.penalty_basis = basis
        self._demo_returns = None

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
        self._demo_returns = None
        self.cost_weights = _weights(cost_weights, "cost_weights", self.l_c)

    def add(self, obs: np.ndarray, next_obs: np.ndarray, action: np.ndarray,
            reward: np.ndarray, done: np.ndarray, infos: list[dict[str, Any]]) -> None:
        """Store a step of all ``n_envs`` envs with the features of the next states."""
        # SB3 replaces next_obs of done envs by their terminal observation but leaves
        # infos alone: info["state"] is the (float64) state the step ended in.
        states = np.array([step_fields(info, ("state",))[0] for info in infos],
                          dtype=np.float64)
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
                             self._penalty_features(self.cost_features, self.next_states,
                                                    (batch_inds, env_indices)),
                             self.reward_scale[batch_inds, env_indices])

    def _penalty_features(self, stored: np.ndarray, next_states: np.ndarray,
                          rows: Any) -> np.ndarray:
        """``[B, l_c]``: the features of the penalty at ``rows`` of ``stored`` (the cost
        features), or of :attr:`penalty_basis` at the same rows of ``next_states``."""
        if self.penalty_basis is None:
            return stored[rows]
        return _features(self.penalty_basis, next_states[rows])

    def _relabel(self, phi_r: np.ndarray, phi_c: np.ndarray, scale: np.ndarray) -> np.ndarray:
        """``[B, n_rewards]`` float64 ``scale · (φ_r · ω_r + λ φ_c · ω_c)`` under the
        current weights, split into per-agent shares when ``per_agent`` and into the
        reward and the cost part when ``split_cost``."""
        if self.reward_weights is None:
            raise RuntimeError(
                "FeatureReplayBuffer has no weights yet; call set_weights(reward_weights, "
                "multiplier, cost_weights) before sampling."
            )
        phi_r, phi_c = phi_r.astype(np.float64), phi_c.astype(np.float64)
        if self.shares is None:
            reward = (phi_r @ self.reward_weights)[:, None]
            cost = self.multiplier * (phi_c @ self.cost_weights)[:, None]
        else:
            share_r, share_c = self.shares
            reward = phi_r @ (self.reward_weights[:, None] * share_r)
            cost = self.multiplier * (phi_c @ (self.cost_weights[:, None] * share_c))
        if self.split_cost:
            return scale[:, None] * np.concatenate([reward, cost], axis=1)
        return scale[:, None] * (reward + cost)

    def set_demonstrations(self, demos: Any, fraction: float,
                           obs_from_states: Callable[[np.ndarray], np.ndarray] | None = None,
                           to_policy: Callable[[np.ndarray], np.ndarray] | None = None
                           ) -> None:
        """Mix demonstrated transitions into every batch (``None`` removes them).

        Each episode of length ``L`` gives ``L`` transitions ``(o_t, a_t, o_{t+1})``, with
        the features of ``s_{t+1}``: the same record as an env transition, so the same
        relabelling applies. The last one is terminal (and absorbing) when the buffer is
        absorbing (episodes end at the goal); otherwise an episode ends at the time
        limit, which SAC bootstraps past, as it does an env's truncation (a terminal
        end there would tell the critic that the goal state is worth one step). SAC is
        off-policy, so this leaves the soft-optimal policy it converges to unchanged; it
        shows the critic routes round the obstacles that its own exploration, starting
        from a policy that heads straight for the goal, rarely finds.

        Args:
            demos: the learner's own episodes (never another learner's):
                :class:`~dicrl_torch.demos.continuous.ContinuousDemonstrations` (or with
                ``to_continuous()``) of the env's shapes (the solver checks them).
            fraction: share of each batch drawn from them, in ``[0, 1)``.
            obs_from_states: the env's observations ``[..., obs_dim]`` of joint states
                ``[..., N, d_s]`` (the joint env's ``obs_from_states``).
            to_policy: maps env actions ``[n, d]`` onto SAC's ``[-1, 1]^d`` (as SB3 stores
                actions); None: they are already there.
        """
        fraction = _check_fraction(fraction, "fraction")
        if demos is None:
            self._demo, self.demo_fraction = None, 0.0
            return
        demos = as_continuous(demos)
        if obs_from_states is None:
            raise ValueError("set_demonstrations needs obs_from_states (the joint env's), to "
                             "give the demonstrated transitions the env's observations.")
        lengths = np.asarray(demos.lengths)
        episode = np.repeat(np.arange(demos.n_episodes), lengths)  # [n] transition -> episode
        t = np.concatenate([np.arange(n) for n in lengths])  # [n] its step in the episode
        states, next_states = demos.states[episode, t], demos.states[episode, t + 1]
        terminal = t == lengths[episode] - 1
        actions = demos.actions[episode, t].reshape(len(t), -1)  # [n, N d_a] agent-major
        self._demo = {
            "obs": obs_from_states(states),
            "next_obs": obs_from_states(next_states),
            "actions": np.asarray(actions if to_policy is None else to_policy(actions),
                                  dtype=np.float32),
            "dones": (terminal & self.absorbing).astype(np.float32),
            "ends": terminal,
            "phi_r": _features(self.reward_basis, next_states),
            "phi_c": _features(self.cost_basis, next_states),
            "scale": np.where(terminal & self.absorbing, 1.0 / (1.0 - self.gamma), 1.0),
            "next_states": np.asarray(next_states, dtype=np.float64),
        }
        self._demo_returns = None
        self.demo_fraction = fraction

    def sampled_demo_returns(self) -> torch.Tensor:
        """``[n_demo, n_rewards]`` float32 on the buffer's device: :meth:`demo_returns` of
        the demonstrated rows of the last :meth:`sample` (its last ``n_demo`` rows)."""
        if self.last_demo_indices is None:
            raise RuntimeError("The last sample held no demonstrated rows: set "
                               "demo_fraction > 0 and call sample first.")
        return self.to_torch(self.demo_returns()[self.last_demo_indices].astype(np.float32))

    def demo_returns(self) -> np.ndarray:
        """``[n, n_rewards]`` float64: each demonstrated transition's discounted return to
        the end of its episode under the current weights, ``G_t = r_t + γ G_{t+1}`` (the
        last transition's ``r`` carries the absorbing scale when the buffer is absorbing).
        The demonstrated actions followed by the rest of the demonstration earn it, so
        it is a lower bound of the optimal value of ``(o_t, a_t)`` (the entropy bonus
        aside) where the rewards after the episode's end are not negative."""
        if self._demo is None:
            raise RuntimeError("No demonstrations: call set_demonstrations first.")
        if self._demo_returns is None:
            d = self._demo
            phi_c = self._penalty_features(d["phi_c"], d["next_states"], slice(None))
            rewards = self._relabel(d["phi_r"], phi_c, d["scale"])  # [n, G]
            returns = np.empty_like(rewards)
            running = np.zeros(rewards.shape[1])
            # transitions lie in episode order, t ascending
            for i in range(len(rewards) - 1, -1, -1):
                if d["ends"][i]:
                    running = np.zeros_like(running)
                running = rewards[i] + self.gamma * running
                returns[i] = running
            self._demo_returns = returns
        return self._demo_returns

    def demo_rows(self, batch_size: int) -> int:
        """How many of a :meth:`sample` of ``batch_size`` are demonstrated transitions
        (its last rows)."""
        return 0 if self._demo is None else int(round(batch_size * self.demo_fraction))

    def sample(self, batch_size: int, env: VecNormalize | None = None) -> ReplayBufferSamples:
        """A batch of ``batch_size`` transitions: :meth:`demo_rows` demonstrated ones (if
        any) after those from the env."""
        n_demo = self.demo_rows(batch_size)
        online = super().sample(batch_size - n_demo, env=env)
        self.last_demo_indices = None
        if n_demo == 0:
            return online
        d = self._demo
        idx = np.random.randint(0, len(d["dones"]), size=n_demo)  # noqa: NPY002 (as SB3)
        self.last_demo_indices = idx
        demo = self._samples(
            d["obs"][idx], d["actions"][idx], d["next_obs"][idx], d["dones"][idx],
            self._relabel(d["phi_r"][idx],
                          self._penalty_features(d["phi_c"], d["next_states"], idx),
                          d["scale"][idx]), env)
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

    # ---- state ----------------------------------------------------------------------
    _STORED = ("observations", "next_observations", "actions", "rewards", "dones",
               "timeouts", "next_states", "reward_features", "cost_features", "reward_scale")
    """The per-transition arrays (``[buffer_size, n_envs, ...]``)."""
    _FRESH = {"reward_scale": 1.0}  # what a new buffer holds in the rows not filled yet (else 0)
    _DEMO = ("obs", "next_obs", "actions", "dones", "ends", "phi_r", "phi_c", "scale",
             "next_states")
    _DEMO_LATER = ("ends", "next_states")  # states saved before these were kept lack them

    def state_dict(self) -> dict[str, Any]:
        """What sampling and storing read, as tensors and plain values: the filled rows
        of the stored transitions (a new buffer holds its defaults in the others),
        ``pos``, ``full``, the weights, the demonstrated transitions and their share, and
        the last sample's indices."""
        n = self.buffer_size if self.full else self.pos
        demo = self._demo
        last = self.last_sample_indices
        return {
            "pos": int(self.pos), "full": bool(self.full),
            "stored": {name: tensor_of(getattr(self, name)[:n]) for name in self._STORED},
            "reward_weights": optional_tensor(self.reward_weights),
            "multiplier": self.multiplier,
            "cost_weights": optional_tensor(self.cost_weights),
            "demo_fraction": float(self.demo_fraction),
            "demo": None if demo is None else {k: tensor_of(demo[k]) for k in self._DEMO
                                               if demo.get(k) is not None},
            "last_sample_indices": None if last is None else [tensor_of(a) for a in last],
        }

    def check_state(self, sd: dict[str, Any]) -> None:
        """A ValueError naming the first field of a :meth:`state_dict` that does not fit
        this buffer (its size, envs, features or dtypes)."""
        pos, full = int(sd["pos"]), bool(sd["full"])
        if not 0 <= pos < self.buffer_size:
            raise ValueError(f"replay buffer: the state's pos {pos} lies outside this "
                             f"buffer's {self.buffer_size} rows per env (buffer_size / "
                             f"n_envs); load a state saved by a solver built with the same "
                             f"arguments.")
        n = self.buffer_size if full else pos
        for name in self._STORED:
            mine = getattr(self, name)
            check_tensor(f"replay buffer field {name!r}", sd["stored"][name],
                         (n, *mine.shape[1:]), torch_dtype(mine.dtype))
        check_optional_array("replay buffer reward_weights", sd["reward_weights"],
                             np.zeros(self.l_r) if sd["reward_weights"] is not None else None)
        check_optional_array("replay buffer cost_weights", sd["cost_weights"],
                             np.zeros(self.l_c) if sd["cost_weights"] is not None else None)
        if sd["demo"] is not None:
            k = int(sd["demo"]["dones"].shape[0])
            mine = {"obs": (k, *self.obs_shape), "next_obs": (k, *self.obs_shape),
                    "actions": (k, self.action_dim), "dones": (k,), "phi_r": (k, self.l_r),
                    "phi_c": (k, self.l_c), "scale": (k,), "ends": (k,),
                    "next_states": (k, *self.state_shape)}
            for key, shape in mine.items():
                if key in self._DEMO_LATER and key not in sd["demo"]:
                    continue  # a state saved before it was kept
                check_tensor(f"replay buffer demonstrations {key!r}", sd["demo"][key], shape,
                             sd["demo"][key].dtype)

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        """Set this buffer to a :meth:`state_dict` (checked first)."""
        self.check_state(sd)
        self.pos, self.full = int(sd["pos"]), bool(sd["full"])
        n = self.buffer_size if self.full else self.pos
        for name in self._STORED:
            arr = getattr(self, name)
            arr[:n] = array_of(sd["stored"][name])
            arr[n:] = self._FRESH.get(name, 0)
        self.reward_weights = optional_array(sd["reward_weights"])
        self.multiplier = None if sd["multiplier"] is None else float(sd["multiplier"])
        self.cost_weights = optional_array(sd["cost_weights"])
        self.demo_fraction = float(sd["demo_fraction"])
        demo = sd["demo"]
        if demo is not None and "ends" not in demo:  # saved before "ends" was kept
            demo = {**demo, "ends": demo["dones"].bool()}
        self._demo = None if demo is None else {
            k: array_of(demo[k]) if k in demo else None for k in self._DEMO}
        self._demo_returns = None
        last = sd["last_sample_indices"]
        self.last_sample_indices = None if last is None else (array_of(last[0]),
                                                              array_of(last[1]))
