"""Planning on a learned constrained game with the nominal model the learner knows.

A learner of the paper's setting knows the nominal dynamics (docs/design.md §7: the solver
trains in ``env_factory(constrained=False)``); only the constraints are unknown. Once it
has learned ``(η̄, ω_c)`` it can act by planning in that model instead of by a policy
network: receding-horizon search for the action sequence of highest learned return

    Σ_t γ^t (ω_r·φ_r(s_{t+1}) + λ ω_c·φ_c(s_{t+1})) + γ^H V(s_H),

never entering a learned constraint (``ω_c,j >= threshold``, grown by a margin), with ``V``
a value of the position alone that sees round the learned obstacles (:func:`grid_values`).
This module holds the two game-free pieces; the drone arena's glue is in
:mod:`dicrl_torch.runs.drones` (docs/drones.md, "Planning on the learned game").

- :func:`grid_values`: for one agent flying at a top speed between the centres of a square
  grid, the value of each centre under a per-centre reward, with forbidden centres and
  absorbing goal centres: the best of staying for ever and moving to a neighbour.
- :class:`CrossEntropyPlanner`: the cross-entropy method over piecewise-constant action
  sequences, re-planned every step, warm-started from the previous plan.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

__all__ = ["CrossEntropyPlanner", "grid_values"]

FORBIDDEN_VALUE = -1e9
"""The return of a plan, or the value of a grid centre, inside a learned constraint."""

_NEIGHBOURS = [(di, dj) for di in (-1, 0, 1) for dj in (-1, 0, 1) if (di, dj) != (0, 0)]


def grid_values(reward: np.ndarray, forbidden: np.ndarray, goal: np.ndarray, *,
                steps_per_cell: float, gamma: float, tol: float = 1e-8,
                max_iterations: int = 10_000) -> np.ndarray:
    """Values ``[G, G]`` of the centres of a square grid for one agent.

    The agent earns ``reward[i, j]`` per time step at centre ``(i, j)`` (row ``i``: y,
    column ``j``: x). From a centre it either stays for ever, worth ``r / (1 - γ)``, or
    moves to one of its 8 neighbours in ``k = steps_per_cell · |(di, dj)|`` time steps,
    earning ``r`` of the centre it leaves meanwhile:

        V(p) = max(r(p) / (1 - γ), max_q (1 - γ^k) / (1 - γ) · r(p) + γ^k V(q)).

    A goal centre is absorbing (``V = r / (1 - γ)``, the agent's state at its goal earns
    for ever), a forbidden one is worth :data:`FORBIDDEN_VALUE` and is never entered.
    Value iteration from the stay values; it is a γ-contraction, so it converges.

    Args:
        reward: ``[G, G]`` per-step reward of each centre.
        forbidden: ``[G, G]`` bool, centres inside a learned constraint.
        goal: ``[G, G]`` bool, absorbing centres.
        steps_per_cell: time steps to fly from a centre to its side neighbour.
        gamma: discount in ``(0, 1)``.
        tol: stop when no value changes by more than this.
        max_iterations: a bound on the sweeps (a RuntimeError past it).

    Returns:
        ``[G, G]`` float64 values.
    """
    reward = np.asarray(reward, dtype=np.float64)
    if reward.ndim != 2 or reward.shape[0] != reward.shape[1]:
        raise ValueError(f"reward must be a square [G, G] array, got shape {reward.shape}.")
    forbidden, goal = np.asarray(forbidden, bool), np.asarray(goal, bool)
    if forbidden.shape != reward.shape or goal.shape != reward.shape:
        raise ValueError(f"forbidden {forbidden.shape} and goal {goal.shape} must have the "
                         f"reward's shape {reward.shape}.")
    if not np.isfinite(reward).all():
        raise ValueError("reward holds NaN or infinite values.")
    if not 0.0 < gamma < 1.0:
        raise ValueError(f"gamma must lie in (0, 1), got {gamma!r}.")
    if not steps_per_cell > 0:
        raise ValueError(f"steps_per_cell must be > 0, got {steps_per_cell!r}.")
    G = reward.shape[0]
    stay = reward / (1.0 - gamma)
    values = np.where(forbidden, FORBIDDEN_VALUE, stay)
    moves = []
    for di, dj in _NEIGHBOURS:
        k = steps_per_cell * float(np.hypot(di, dj))
        moves.append((di, dj, (1.0 - gamma**k) / (1.0 - gamma) * reward, gamma**k))
    for _ in range(max_iterations):
        best = values.copy()
        for di, dj, earned, discount in moves:
            # neighbour[i, j] = values[i + di, j + dj] where that centre exists
            neighbour = np.full_like(values, -np.inf)
            neighbour[max(-di, 0):G - max(di, 0), max(-dj, 0):G - max(dj, 0)] = \
                values[max(di, 0):G - max(-di, 0), max(dj, 0):G - max(-dj, 0)]
            best = np.maximum(best, earned + discount * neighbour)
        best = np.where(goal, stay, np.where(forbidden, FORBIDDEN_VALUE, best))
        if np.abs(best - values).max() <= tol:
            return best
        values = best
    raise RuntimeError(f"grid_values did not converge in {max_iterations} sweeps; raise "
                       f"max_iterations or tol.")


class CrossEntropyPlanner:
    """Receding-horizon cross-entropy planning in a batched model.

    A plan is ``horizon // knot`` actions, each held for ``knot`` steps. Every call of
    :meth:`act` samples ``samples`` plans round the current mean (the previous plan
    shifted by the steps taken since, the mean itself always among them), rolls them out
    in ``step_fn``, scores them, refits mean and spread to the ``elites`` best, and after
    ``iterations`` rounds returns the first action of the mean.

    Args:
        step_fn: ``(states [B, ...], active [B, N], actions [B, *action_shape]) ->
            (states, active)``: the nominal model, batched and pure.
        reward_fn: ``states [T, B, ...] -> [T, B]`` the per-step reward of reaching them.
        forbidden_fn: ``states [T, B, ...] -> [T, B]`` bool, inside a constraint.
        terminal_fn: ``states [B, ...] -> [B]`` the value of the plan's last state when the
            episode has not ended in it.
        action_shape: shape of one action, e.g. ``(N, 2)``; actions lie in ``[-1, 1]``.
        gamma: discount in ``(0, 1)``.
        horizon, knot: steps planned, and steps each planned action is held.
        samples, iterations, elites: the cross-entropy method's sizes.
        init_std: spread of the first round round a zero (or warm) mean.
        seed: the planner's own random stream.

    A plan that reaches a state where no agent is active ends there: that state is
    absorbing (its reward earned for ever, ``1 / (1 - γ)``), as in the SAC solver.
    """

    def __init__(self, *, step_fn: Callable, reward_fn: Callable, forbidden_fn: Callable,
                 terminal_fn: Callable, action_shape: tuple[int, ...], gamma: float,
                 horizon: int = 30, knot: int = 5, samples: int = 256, iterations: int = 4,
                 elites: int = 25, init_std: float = 0.6, seed: int = 0) -> None:
        for name, value in (("horizon", horizon), ("knot", knot), ("samples", samples),
                            ("iterations", iterations), ("elites", elites)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be a positive int, got {value!r}.")
        if horizon % knot:
            raise ValueError(f"horizon={horizon} must be a multiple of knot={knot}.")
        if elites > samples:
            raise ValueError(f"elites={elites} exceeds samples={samples}.")
        if not 0.0 < gamma < 1.0:
            raise ValueError(f"gamma must lie in (0, 1), got {gamma!r}.")
        self.step_fn, self.reward_fn = step_fn, reward_fn
        self.forbidden_fn, self.terminal_fn = forbidden_fn, terminal_fn
        self.action_shape = tuple(action_shape)
        self.gamma, self.horizon, self.knot = float(gamma), horizon, knot
        self.samples, self.iterations, self.elites = samples, iterations, elites
        self.init_std = float(init_std)
        self.rng = np.random.default_rng(seed)
        self.reset()

    def reset(self) -> None:
        """Forget the previous plan (at the start of an episode)."""
        self._mean = np.zeros((self.horizon // self.knot, *self.action_shape))
        self._held = 0  # steps the first planned action has been held

    def returns(self, state: Any, active: Any, knots: np.ndarray) -> np.ndarray:
        """``[B]`` learned returns of plans ``knots [B, K, *action_shape]`` from ``state``
        (lowered by :data:`FORBIDDEN_VALUE` for a plan entering a constraint before it
        ends)."""
        B = knots.shape[0]
        actions = np.repeat(knots, self.knot, axis=1)[:, self._held:][:, :self.horizon]
        states = np.repeat(np.asarray(state)[None], B, 0)
        flying = np.repeat(np.asarray(active, bool)[None], B, 0)
        trajectory, alive = [], []
        for t in range(actions.shape[1]):
            states, flying = self.step_fn(states, flying, actions[:, t])
            trajectory.append(states)
            alive.append(np.asarray(flying).any(-1))
        trajectory, alive = np.stack(trajectory), np.stack(alive)  # [T, B, ...], [T, B]
        T = len(alive)
        before = np.concatenate([np.ones((1, B), bool), alive[:-1]])  # running before t
        ends = before & ~alive
        discount = self.gamma ** np.arange(T)[:, None]
        reward = np.asarray(self.reward_fn(trajectory), dtype=np.float64)
        scale = np.where(ends, 1.0 / (1.0 - self.gamma), 1.0)
        total = np.where(before, discount * scale * reward, 0.0).sum(0)
        total = total + np.where(alive[-1], self.gamma**T
                                 * np.asarray(self.terminal_fn(trajectory[-1])), 0.0)
        entered = (np.asarray(self.forbidden_fn(trajectory), bool) & before).any(0)
        # Below every plan that keeps out, still ranked by return among themselves.
        return np.where(entered, total + FORBIDDEN_VALUE, total)

    def act(self, state: Any, active: Any) -> np.ndarray:
        """The next action ``[*action_shape]`` from ``state`` with ``active`` agents."""
        mean = self._mean
        std = np.full_like(mean, self.init_std)
        for _ in range(self.iterations):
            knots = mean[None] + std[None] * self.rng.standard_normal((self.samples,
                                                                       *mean.shape))
            knots = np.clip(knots, -1.0, 1.0)
            knots[0] = mean
            scores = self.returns(state, active, knots)
            elite = knots[np.argsort(-scores, kind="stable")[:self.elites]]
            mean, std = elite.mean(0), elite.std(0) + 0.05
        action = mean[0].copy()
        # Hold the first knot for `knot` steps, then shift the plan by one knot.
        self._held += 1
        if self._held == self.knot:
            mean = np.concatenate([mean[1:], mean[-1:]])
            self._held = 0
        self._mean = mean
        return action
