"""Planning on a learned constrained game with the nominal model the learner knows.

A learner of the paper's setting knows the nominal dynamics (docs/design.md §7: the solver
trains in ``env_factory(constrained=False)``); only the constraints are unknown. Once it
has learned ``(η̄, ω_c)`` it can act by planning in that model instead of by a policy
network: receding-horizon search for the action sequence of highest learned return

    Σ_t γ^t (ω_r·φ_r(s_{t+1}) + λ ω_c·φ_c(s_{t+1})) + γ^H V(s_H),

never entering a learned constraint (``ω_c,j >= threshold``, grown by a margin), with ``V``
a value of the position alone that sees round the learned obstacles (:func:`grid_values`).
This module holds the two game-free pieces; the drone arena's are in
:mod:`dicrl_torch.solvers.drone_planning` (docs/drones.md, "Planning on the learned game").

- :func:`grid_values`: for one agent flying at a top speed between the centres of a square
  grid, the value of each centre under a per-centre reward, with forbidden centres and
  absorbing goal centres: the best of staying for ever and moving to a neighbour.
- :class:`CrossEntropyPlanner`: the cross-entropy method over piecewise-constant action
  sequences, re-planned every step, warm-started from the previous plan, for many
  independent problems (episodes) in one batched model call.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from dicrl_torch.checks import InvalidSetting, setting_int

__all__ = ["PLAN_SIZES", "CrossEntropyPlanner", "check_plan_sizes", "grid_values"]

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


PLAN_SIZES: tuple[str, ...] = ("horizon", "knot", "replan", "samples", "iterations", "elites")
"""The planner's integer sizes, :func:`check_plan_sizes`' keywords (a config's, a task's)."""


def check_plan_sizes(*, horizon: int, knot: int, replan: int, samples: int, iterations: int,
                     elites: int) -> None:
    """Refuse :class:`CrossEntropyPlanner`'s sizes unless they fit together: positive
    ints, whole held commands in the horizon, re-plans on a command's steps, elites among
    the samples (also for settings checked before any planner is built).

    Raises:
        InvalidSetting: naming the size at fault (and the one it must fit).
    """
    for name, value, example in (("horizon", horizon, 30), ("knot", knot, 5),
                                 ("replan", replan, 1), ("samples", samples, 256),
                                 ("iterations", iterations, 4), ("elites", elites, 25)):
        setting_int(name, value, example=example)
    if horizon % knot:
        raise InvalidSetting("horizon", horizon, f"an int >= 1, a multiple of {{knot}}={knot} "
                             f"(whole held commands)", knot * max(1, round(horizon / knot)))
    if knot % replan:
        raise InvalidSetting("replan", replan, f"an int >= 1 dividing {{knot}}={knot} (re-plans "
                             f"fall on the held command's steps)", knot)
    if elites > samples:
        raise InvalidSetting("elites", elites, f"an int >= 1, at most {{samples}}={samples} (the "
                             f"best plans refitted to)", max(1, samples // 10))


class CrossEntropyPlanner:
    """Receding-horizon cross-entropy planning in a batched model, for several
    independent problems at once (e.g. one per evaluation episode).

    A plan is ``horizon // knot`` actions, each held for ``knot`` steps. Every call of
    :meth:`act` samples, for each problem asked, ``samples`` plans round its current mean
    (at first its previous plan shifted by the steps taken since, the mean itself always
    among them), rolls out the plans of all those problems in one ``step_fn`` call per
    step, scores them, refits each problem's mean and spread to its ``elites`` best, and
    after ``iterations`` rounds returns the first action of the best plan it scored (which
    the next call starts from, so a plan found is kept until a better one is). Each problem
    draws from its own random stream, so its plans do not depend on which other problems
    are planned beside it (batching is for speed: one model call on ``P × samples`` states
    instead of ``P`` calls on ``samples``).

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
        replan: re-plan every ``replan`` steps (a divisor of ``knot``); in between the
            plan's held action is flown as it is. 1 (the default): every step; ``knot``:
            once per planned action, ``knot`` times fewer rollouts.
        samples, iterations, elites: the cross-entropy method's sizes (per problem).
        init_std: spread of the first round round a zero (or warm) mean.
        seed: one problem's random stream, or a sequence of seeds, one problem each.

    A plan that reaches a state where no agent is active ends there: that state is
    absorbing (its reward earned for ever, ``1 / (1 - γ)``), as in the SAC solver.
    """

    def __init__(self, *, step_fn: Callable, reward_fn: Callable, forbidden_fn: Callable,
                 terminal_fn: Callable, action_shape: tuple[int, ...], gamma: float,
                 horizon: int = 30, knot: int = 5, replan: int = 1, samples: int = 256,
                 iterations: int = 4, elites: int = 25, init_std: float = 0.6,
                 seed: int | Sequence[int] = 0) -> None:
        check_plan_sizes(horizon=horizon, knot=knot, replan=replan, samples=samples,
                         iterations=iterations, elites=elites)
        if not 0.0 < gamma < 1.0:
            raise ValueError(f"gamma must lie in (0, 1), got {gamma!r}.")
        seeds = [seed] if isinstance(seed, (int, np.integer)) else list(seed)
        if not seeds:
            raise ValueError("seed must be an int or a non-empty sequence of ints (one "
                             "problem per seed).")
        self.step_fn, self.reward_fn = step_fn, reward_fn
        self.forbidden_fn, self.terminal_fn = forbidden_fn, terminal_fn
        self.action_shape = tuple(action_shape)
        self.gamma, self.horizon, self.knot, self.replan = float(gamma), horizon, knot, replan
        self.samples, self.iterations, self.elites = samples, iterations, elites
        self.init_std = float(init_std)
        self.rngs = [np.random.default_rng(int(s)) for s in seeds]
        self.reset()

    @property
    def problems(self) -> int:
        """The number of independent problems planned for."""
        return len(self.rngs)

    def reset(self) -> None:
        """Forget every problem's previous plan (before a new set of episodes)."""
        self._plan = np.zeros((self.problems, self.horizon // self.knot, *self.action_shape))
        self._held = np.zeros(self.problems, dtype=np.int64)  # steps the first action held

    def returns(self, states: Any, active: Any, knots: np.ndarray, held: int = 0
                ) -> np.ndarray:
        """``[P, S]`` learned returns of plans ``knots [P, S, K, *action_shape]`` from
        problem ``p``'s ``states[p]`` with ``active [P, N]`` agents, the first knot already
        held for ``held`` steps (lowered by :data:`FORBIDDEN_VALUE` for a plan entering a
        constraint before it ends)."""
        P, S = knots.shape[:2]
        B = P * S
        actions = np.repeat(knots, self.knot, axis=2)[:, :, held:][:, :, :self.horizon]
        actions = actions.reshape(B, actions.shape[2], *self.action_shape)
        # Problem-major: rows p*S .. p*S + S - 1 are problem p's plans.
        states = np.repeat(np.asarray(states), S, 0)
        flying = np.repeat(np.asarray(active, bool), S, 0)
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
        return np.where(entered, total + FORBIDDEN_VALUE, total).reshape(P, S)

    def act(self, states: Any, active: Any, which: Any = None) -> np.ndarray:
        """The next actions ``[P', *action_shape]`` of problems ``which [P']`` (default
        all, in order) from their ``states [P', ...]`` with ``active [P', N]`` agents."""
        which = (np.arange(self.problems) if which is None
                 else np.asarray(which, dtype=np.int64).reshape(-1))
        states, active = np.asarray(states), np.asarray(active, bool)
        if len(states) != len(which) or len(active) != len(which):
            raise ValueError(f"states ({len(states)}) and active ({len(active)}) need one row "
                             f"per problem asked ({len(which)}).")
        if len(which) and (which.min() < 0 or which.max() >= self.problems
                           or len(np.unique(which)) != len(which)):
            raise ValueError(f"which must hold distinct problems in [0, {self.problems}), "
                             f"got {which.tolist()}.")
        out = np.empty((len(which), *self.action_shape))
        # Problems whose first knot has been held equally long share one rollout batch.
        for held in np.unique(self._held[which]):
            rows = np.flatnonzero(self._held[which] == held)
            out[rows] = self._act_held(states[rows], active[rows], which[rows], int(held))
        return out

    def _act_held(self, states: np.ndarray, active: np.ndarray, which: np.ndarray,
                  held: int) -> np.ndarray:
        """:meth:`act` for problems ``which`` whose first knot has been held ``held``
        steps."""
        plan = self._plan[which]  # [P', K, *A]: the previous step's plan, shifted
        mean, std = plan, np.full_like(plan, self.init_std)
        best_score = np.full(len(which), -np.inf)
        spare = (None,) * (mean.ndim - 1)
        rounds = self.iterations if held % self.replan == 0 else 0
        for _ in range(rounds):
            noise = np.stack([self.rngs[p].standard_normal((self.samples, *mean.shape[1:]))
                              for p in which])
            knots = np.clip(mean[:, None] + std[:, None] * noise, -1.0, 1.0)
            knots[:, 0] = mean
            scores = self.returns(states, active, knots, held)
            order = np.argsort(-scores, axis=1, kind="stable")
            elite = np.take_along_axis(knots, order[:, :self.elites][(...,) + spare], axis=1)
            # The plan flown is the best one scored, never the elites' mean: the mean of
            # plans passing a learned obstacle on either side runs into it (and is never
            # scored), and a drone flying such means hovers at the obstacle.
            top = scores.max(1)  # elite[:, 0]'s
            better = top > best_score
            plan = np.where(better[(...,) + spare], elite[:, 0], plan)
            best_score = np.where(better, top, best_score)
            mean, std = elite.mean(1), elite.std(1) + 0.05
        action = plan[:, 0].copy()
        # Hold the first knot for `knot` steps, then shift the plan by one knot.
        held += 1
        if held == self.knot:
            plan = np.concatenate([plan[:, 1:], plan[:, -1:]], axis=1)
            held = 0
        self._plan[which], self._held[which] = plan, held
        return action
