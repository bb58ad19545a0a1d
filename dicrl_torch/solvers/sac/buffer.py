"""The SAC solver's replay buffer: features stored, rewards relabelled on sampling.

See :mod:`dicrl_torch.solvers.sac` ("No stale rewards", "Absorbing termination").
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.type_aliases import ReplayBufferSamples
from stable_baselines3.common.vec_env import VecNormalize
from torch import nn

from dicrl_torch.solvers.sac.features import _features
from dicrl_torch.solvers.sac.labels import RewardLabels
from dicrl_torch.solvers.sac.protocol import step_fields
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


class FeatureReplayBuffer(RewardLabels, ReplayBuffer):
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
        self._init_labels(reward_basis=reward_basis, cost_basis=cost_basis, gamma=gamma,
                          absorbing=absorbing, state_shape=state_shape, per_agent=per_agent,
                          split_cost=split_cost)
        shape = (self.buffer_size, self.n_envs)
        self.next_states = np.zeros((*shape, *self.state_shape), dtype=np.float64)
        self.reward_features = np.zeros((*shape, self.l_r), dtype=feature_dtype)
        self.cost_features = np.zeros((*shape, self.l_c), dtype=feature_dtype)
        self.reward_scale = np.ones(shape, dtype=np.float64)
        self.last_sample_indices: tuple[np.ndarray, np.ndarray] | None = None
        """``(batch_inds, env_indices)`` of the last :meth:`sample`'s transitions from
        the env, for inspection."""
        self.last_demo_indices: np.ndarray | None = None
        """``[n_demo]``: the demonstrated transitions of the last :meth:`sample`'s last
        rows (None without any); their returns are computed only when asked for."""

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
        self.reward_scale[pos] = self.terminal_scale(terminal)
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

    def sampled_demo_returns(self) -> torch.Tensor:
        """``[n_demo, n_rewards]`` float32 on the buffer's device: :meth:`demo_returns` of
        the demonstrated rows of the last :meth:`sample` (its last ``n_demo`` rows)."""
        if self.last_demo_indices is None:
            raise RuntimeError("The last sample held no demonstrated rows: set "
                               "demo_fraction > 0 and call sample first.")
        return self.to_torch(self.demo_returns()[self.last_demo_indices].astype(np.float32))

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
