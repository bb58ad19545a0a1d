"""The lean loop's replay buffer: one learner's transitions as torch tensors, labelled
once per weight change instead of once per sample.

It stores what :class:`~dicrl_torch.solvers.sac.buffer.FeatureReplayBuffer` stores (the
next state's features and the absorbing scale; never a reward) and labels rows with the
same :class:`~dicrl_torch.solvers.sac.labels.RewardLabels`: every stored row when the
weights or the penalty basis change, a new row when it is added. The labels are those a
relabel at sampling would give (the same float64 arithmetic, cast to float32), but a
batch is then a gather of rows, not ``B`` dot products of ``l_c`` features per update.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import nn

from dicrl_torch.solvers.sac.features import _features
from dicrl_torch.solvers.sac.labels import RewardLabels
from dicrl_torch.solvers.sac.state import (
    array_of,
    check_tensor,
    optional_array,
    optional_tensor,
    tensor_of,
)

__all__ = ["TransitionStore"]

_RELABEL_ROWS = 16_384  # rows per float64 relabelling chunk (bounds its temporary memory)


class TransitionStore(RewardLabels):
    """A ring of ``capacity`` transitions ``(o, a, o', terminal)`` with the features of
    the next state, sampled with a learner's own generator.

    Args:
        capacity: transitions kept (the oldest are overwritten).
        obs_dim, action_dim: sizes of the (already scaled) observations and the actions
            in ``[-1, 1]``.
        reward_basis, cost_basis, gamma, absorbing, state_shape, per_agent, split_cost:
            as :class:`~dicrl_torch.solvers.sac.buffer.FeatureReplayBuffer`.
        feature_dtype: storage dtype of the features.
    """

    def __init__(self, capacity: int, obs_dim: int, action_dim: int, *,
                 reward_basis: nn.Module, cost_basis: nn.Module, gamma: float,
                 absorbing: bool, state_shape: tuple[int, int], per_agent: bool = False,
                 split_cost: bool = False, feature_dtype: Any = np.float32) -> None:
        self._init_labels(reward_basis=reward_basis, cost_basis=cost_basis, gamma=gamma,
                          absorbing=absorbing, state_shape=state_shape, per_agent=per_agent,
                          split_cost=split_cost)
        c = self.capacity = int(capacity)
        self.obs = torch.zeros(c, obs_dim)
        self.next_obs = torch.zeros(c, obs_dim)
        self.actions = torch.zeros(c, action_dim)
        self.dones = torch.zeros(c, 1)
        self.rewards = torch.zeros(c, self.n_rewards)  # labels under the current weights
        self.next_states = np.zeros((c, *self.state_shape))
        self.reward_features = np.zeros((c, self.l_r), dtype=feature_dtype)
        self.cost_features = np.zeros((c, self.l_c), dtype=feature_dtype)
        self.reward_scale = np.ones(c)
        self.pos, self.size = 0, 0
        self._demo_torch: dict[str, torch.Tensor] | None = None

    # ---- storing ------------------------------------------------------------------
    def add(self, obs: np.ndarray, next_obs: np.ndarray, actions: np.ndarray,
            terminal: np.ndarray, next_states: np.ndarray) -> None:
        """Store ``n`` transitions: observations ``[n, d_o]`` (scaled), actions
        ``[n, d_a]`` in ``[-1, 1]``, ``terminal`` ``[n]`` (not a time limit) and the
        joint states they ended in ``[n, N, d_s]``."""
        n = len(obs)
        rows = (self.pos + np.arange(n)) % self.capacity
        self.next_states[rows] = next_states
        self.reward_features[rows] = _features(self.reward_basis, next_states)
        self.cost_features[rows] = _features(self.cost_basis, next_states)
        self.reward_scale[rows] = self.terminal_scale(terminal)
        idx = torch.from_numpy(rows)
        self.obs[idx] = torch.as_tensor(obs, dtype=torch.float32)
        self.next_obs[idx] = torch.as_tensor(next_obs, dtype=torch.float32)
        self.actions[idx] = torch.as_tensor(actions, dtype=torch.float32)
        self.dones[idx] = torch.as_tensor(np.asarray(terminal, dtype=np.float32)[:, None])
        if self.reward_weights is not None:
            self.rewards[idx] = self._labels(rows)
        self.pos = int((self.pos + n) % self.capacity)
        self.size = min(self.size + n, self.capacity)

    def _labels(self, rows: Any) -> torch.Tensor:
        """``[n, G]`` float32 labels of stored ``rows`` under the current weights."""
        phi_c = self._penalty_features(self.cost_features, self.next_states, rows)
        return torch.from_numpy(self._relabel(self.reward_features[rows], phi_c,
                                              self.reward_scale[rows]).astype(np.float32))

    def _label_all(self) -> None:
        """Relabel every stored row and the demonstrations (after a weight change)."""
        self._demo_returns = None
        if self.reward_weights is None:
            return
        for start in range(0, self.size, _RELABEL_ROWS):
            rows = slice(start, min(start + _RELABEL_ROWS, self.size))
            self.rewards[rows] = self._labels(rows)
        if self._demo is not None:
            d = self._demo
            phi_c = self._penalty_features(d["phi_c"], d["next_states"], slice(None))
            self._demo_torch["rewards"] = torch.from_numpy(
                self._relabel(d["phi_r"], phi_c, d["scale"]).astype(np.float32))

    def set_weights(self, reward_weights: Any, multiplier: Any, cost_weights: Any) -> None:
        super().set_weights(reward_weights, multiplier, cost_weights)
        self._label_all()

    def set_penalty_basis(self, basis: nn.Module | None) -> None:
        super().set_penalty_basis(basis)
        self._label_all()

    def set_demonstrations(self, demos: Any, fraction: float, obs_from_states: Any = None,
                           to_policy: Any = None) -> None:
        """As :meth:`RewardLabels.set_demonstrations`; ``obs_from_states`` must give the
        observations as the networks read them (scaled)."""
        super().set_demonstrations(demos, fraction, obs_from_states, to_policy)
        self._sync_demo()

    def _sync_demo(self) -> None:
        d = self._demo
        self._demo_torch = None if d is None else {
            "obs": torch.as_tensor(d["obs"], dtype=torch.float32),
            "next_obs": torch.as_tensor(d["next_obs"], dtype=torch.float32),
            "actions": torch.as_tensor(d["actions"], dtype=torch.float32),
            "dones": torch.as_tensor(d["dones"], dtype=torch.float32)[:, None]}
        self._label_all()

    # ---- sampling -----------------------------------------------------------------
    def sample(self, batch_size: int, generator: torch.Generator
               ) -> tuple[tuple[torch.Tensor, ...], torch.Tensor | None]:
        """``(obs, actions, rewards, next_obs, dones)`` ``[B, ...]`` float32, the last
        :meth:`demo_rows` rows from the demonstrations, and those rows' demonstration
        indices ``[n_demo]`` (None without any). Indices come from ``generator``."""
        n_demo = self.demo_rows(batch_size)
        idx = torch.randint(self.size, (batch_size - n_demo,), generator=generator)
        fields = (self.obs, self.actions, self.rewards, self.next_obs, self.dones)
        if n_demo == 0:
            return tuple(f.index_select(0, idx) for f in fields), None
        d = self._demo_torch
        demo_idx = torch.randint(len(d["dones"]), (n_demo,), generator=generator)
        demo = (d["obs"], d["actions"], d["rewards"], d["next_obs"], d["dones"])
        return tuple(torch.cat([f.index_select(0, idx), g.index_select(0, demo_idx)])
                     for f, g in zip(fields, demo, strict=True)), demo_idx

    def demo_returns_of(self, demo_idx: torch.Tensor) -> torch.Tensor:
        """``[n_demo, G]`` float32 :meth:`demo_returns` of demonstrations ``demo_idx``."""
        return torch.from_numpy(self.demo_returns()[demo_idx.numpy()].astype(np.float32))

    # ---- state --------------------------------------------------------------------
    _STORED = ("obs", "next_obs", "actions", "dones", "next_states", "reward_features",
               "cost_features", "reward_scale")
    _DEMO = ("obs", "next_obs", "actions", "dones", "ends", "phi_r", "phi_c", "scale",
             "next_states")

    def state_dict(self) -> dict[str, Any]:
        """The filled rows, ``pos``, the weights, the demonstrations and their share (the
        labels are recomputed on load)."""
        n = self.size
        return {"pos": self.pos, "size": n,
                "stored": {k: _copy(getattr(self, k)[:n]) for k in self._STORED},
                "reward_weights": optional_tensor(self.reward_weights),
                "multiplier": self.multiplier,
                "cost_weights": optional_tensor(self.cost_weights),
                "demo_fraction": float(self.demo_fraction),
                "demo": None if self._demo is None
                else {k: tensor_of(self._demo[k]) for k in self._DEMO}}

    def check_state(self, sd: dict[str, Any]) -> None:
        """A ValueError naming the first field of ``sd`` that does not fit this store."""
        pos, n = int(sd["pos"]), int(sd["size"])
        if not (0 <= n <= self.capacity and 0 <= pos < self.capacity):
            raise ValueError(f"replay buffer: the state holds {n} transitions at position "
                             f"{pos}, this buffer {self.capacity} (buffer_size); load a state "
                             f"saved by a solver built with the same arguments.")
        for k in self._STORED:
            mine = getattr(self, k)
            dtype = mine.dtype if isinstance(mine, torch.Tensor) \
                else torch.from_numpy(mine[:0]).dtype
            check_tensor(f"replay buffer field {k!r}", sd["stored"][k], (n, *mine.shape[1:]),
                         dtype)
        for name, dim in (("reward_weights", self.l_r), ("cost_weights", self.l_c)):
            if sd[name] is not None:
                check_tensor(f"replay buffer {name}", sd[name], (dim,), torch.float64)
        for name in ("multiplier", "demo_fraction"):
            if sd[name] is not None:
                float(sd[name])
        if sd["demo"] is not None:  # checked too: a load changes nothing unless it can finish
            k = int(sd["demo"]["dones"].shape[0])
            obs = (k, self.obs.shape[1])
            shapes = {"obs": obs, "next_obs": obs, "actions": (k, self.actions.shape[1]),
                      "dones": (k,), "ends": (k,), "phi_r": (k, self.l_r),
                      "phi_c": (k, self.l_c), "scale": (k,),
                      "next_states": (k, *self.state_shape)}
            for key, shape in shapes.items():
                check_tensor(f"replay buffer demonstrations {key!r}", sd["demo"][key], shape,
                             sd["demo"][key].dtype)

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        """Set this store to a :meth:`state_dict` (checked first)."""
        self.check_state(sd)
        self.pos, self.size = int(sd["pos"]), int(sd["size"])
        n = self.size
        for k in self._STORED:
            mine = getattr(self, k)
            value = sd["stored"][k]
            if isinstance(mine, torch.Tensor):
                mine[:n] = value
                mine[n:] = 0
            else:
                mine[:n] = array_of(value)
                mine[n:] = 1.0 if k == "reward_scale" else 0.0
        self.reward_weights = optional_array(sd["reward_weights"])
        self.multiplier = None if sd["multiplier"] is None else float(sd["multiplier"])
        self.cost_weights = optional_array(sd["cost_weights"])
        self.demo_fraction = float(sd["demo_fraction"])
        self._demo = None if sd["demo"] is None else {k: array_of(v)
                                                      for k, v in sd["demo"].items()}
        self.rewards.zero_()
        self._sync_demo()


def _copy(a: np.ndarray | torch.Tensor) -> torch.Tensor:
    """A tensor copy of a stored field (numpy or torch)."""
    return a.clone() if isinstance(a, torch.Tensor) else tensor_of(a)
