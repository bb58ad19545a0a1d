"""Rewards from stored features: what both replay buffers of the SAC solver share.

A transition is stored with the features of the state it ended in, never with a reward:
the reward ``scale · (φ_r · ω_r + λ φ_c · ω_c)`` is computed from the weights of the
last :meth:`RewardLabels.set_weights` (see :mod:`dicrl_torch.solvers.sac`, "No stale
rewards"), split into per-agent and reward / cost columns for decomposed critics. The
learner's own demonstrated transitions are kept in the same form, so the same labels
apply to them.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
from torch import nn

from dicrl_torch.solvers.sac.checks import _check_fraction, _check_gamma, _weights
from dicrl_torch.solvers.sac.features import _agent_shares, _basis_dim, _features
from dicrl_torch.solvers.sac.protocol import as_continuous

__all__ = ["RewardLabels"]


class RewardLabels:
    """The relabelling and the demonstrated transitions of a feature replay buffer
    (a mixin: :class:`~dicrl_torch.solvers.sac.buffer.FeatureReplayBuffer` and
    :class:`~dicrl_torch.solvers.sac.replay.TransitionStore`)."""

    def _init_labels(self, *, reward_basis: nn.Module, cost_basis: nn.Module, gamma: float,
                     absorbing: bool, state_shape: tuple[int, int], per_agent: bool,
                     split_cost: bool) -> None:
        """Set the bases, the discount, the reward columns and no weights yet."""
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
        self.reward_weights: np.ndarray | None = None
        self.multiplier: float | None = None
        self.cost_weights: np.ndarray | None = None
        self.demo_fraction = 0.0
        self._demo: dict[str, np.ndarray] | None = None
        self._demo_returns: np.ndarray | None = None  # under the current weights
        self.penalty_basis: nn.Module | None = None
        """Set by :meth:`set_penalty_basis`: the basis of the penalty's features, computed
        from the stored next states at sampling (None: the stored ``φ_c``)."""

    def terminal_scale(self, terminal: np.ndarray) -> np.ndarray:
        """``[n]`` float64 reward scale of transitions: ``1 / (1 - γ)`` for a terminal
        one when absorbing (the absorbing state's whole future), else 1."""
        return np.where(np.asarray(terminal, dtype=bool) & self.absorbing,
                        1.0 / (1.0 - self.gamma), 1.0)

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
            "scale": self.terminal_scale(terminal),
            "next_states": np.asarray(next_states, dtype=np.float64),
        }
        self._demo_returns = None
        self.demo_fraction = fraction

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

