"""The experts of the constrained spread (:mod:`dicrl_torch.envs.mpe`) and the episode
runner that flies them: the continuous demonstrations of that game are generated here,
beside the drone arena's planner (:mod:`dicrl_torch.demos.drone_demos`), and recorded and
stored by :mod:`dicrl_torch.demos.continuous`.

- :class:`NominalController`: every agent straight to its landmark, ignoring the
  constraints; it violates both kinds.
- :class:`ViaPointController`: around the disc in lanes, with start delays planned so
  that the agents keep apart; succeeds without violation (the experts).
- :func:`run_episode`: fly one episode of a controller, as an :class:`Episode`.

Both controllers are deterministic given the start state; they read only the env's
public layout and mpe2's physical constants, never its world.
"""

from __future__ import annotations

import itertools
import math
import zlib
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from dicrl_torch.envs.mpe.env import ConstrainedSpread
from dicrl_torch.envs.mpe.layout import (
    MAX_SPEED,
    SUCCESS_RADIUS,
    check_number,
    sorted_assignment,
)

__all__ = ["Controller", "Episode", "NominalController", "ViaPointController", "run_episode"]


# ---------------------------------------------------------------------- controllers
class Controller(Protocol):
    """A joint controller: ``reset(state)`` at the episode start, then ``act(state,
    active) -> [N, 2]`` commands in ``[-1, 1]``."""

    def reset(self, state: np.ndarray) -> None: ...

    def act(self, state: np.ndarray, active: np.ndarray) -> np.ndarray: ...


def _segment_distance(point: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """Least distance from ``point`` to the segment from ``a`` to ``b`` (all ``[2]``)."""
    ab = b - a
    t = float(np.clip((point - a) @ ab / max(ab @ ab, 1e-12), 0.0, 1.0))
    return float(np.linalg.norm(point - (a + t * ab)))


def _velocity_command(env: ConstrainedSpread, vel: np.ndarray, v_des: np.ndarray
                      ) -> np.ndarray:
    """``[N, 2]`` commands that bring velocities ``vel`` to ``v_des`` in one step of
    mpe2's physics (``v' = (1 - damping) v + dt * sensitivity * u / mass``), scaled down
    (direction kept) where they exceed ``[-1, 1]``."""
    u = (v_des - (1 - env.damping) * vel) * env.mass / (env.dt * env.sensitivity)
    scale = np.maximum(np.abs(u).max(-1, keepdims=True), 1.0)
    return u / scale


class _WaypointFollower:
    """Each agent flies its own list of via-points at a cruise speed: proportional
    tracking of the current via-point (speed ``min(cruise, gain * distance)``), the
    next via-point once within ``switch`` of it; the last one is held."""

    def __init__(self, env: ConstrainedSpread, *, cruise_speed: float, gain: float,
                 switch: float) -> None:
        self.env = env
        self.cruise_speed = check_number("cruise_speed", cruise_speed, positive=True)
        self.gain = check_number("gain", gain, positive=True)
        self.switch = switch
        self.routes: list[np.ndarray] = []
        self._next: np.ndarray = np.zeros(0, dtype=np.int64)

    def start(self, routes: list[np.ndarray]) -> None:
        self.routes = routes
        self._next = np.zeros(len(routes), dtype=np.int64)

    def targets(self, pos: np.ndarray) -> np.ndarray:
        out = np.empty_like(pos)
        for i, route in enumerate(self.routes):
            while self._next[i] < len(route) - 1 \
                    and np.linalg.norm(route[self._next[i]] - pos[i]) < self.switch:
                self._next[i] += 1
            out[i] = route[self._next[i]]
        return out

    def desired_velocity(self, state: np.ndarray) -> np.ndarray:
        """``[N, 2]`` velocities towards the current via-points."""
        pos, vel = state[:, :2], state[:, 2:]
        ahead = pos + self.env.dt * vel  # mpe2 moves by the current velocity first
        err = self.targets(ahead) - ahead
        dist = np.linalg.norm(err, axis=-1, keepdims=True)
        return err / np.maximum(dist, 1e-9) * np.minimum(self.cruise_speed, self.gain * dist)

    def command(self, state: np.ndarray, active: np.ndarray, v_des: np.ndarray
                ) -> np.ndarray:
        u = _velocity_command(self.env, state[:, 2:], v_des)
        u[~np.asarray(active, dtype=bool)] = 0.0
        return u.astype(np.float32)

    def act(self, state: np.ndarray, active: np.ndarray) -> np.ndarray:
        return self.command(state, active, self.desired_velocity(state))


class NominalController:
    """The unconstrained expert: every agent flies straight to its landmark
    (:func:`sorted_assignment`, fixed at ``reset``) at ``cruise_speed``, ignoring the
    disc and the other agents. Deterministic.

    Args:
        env: the game (for its layout and mpe2's physical constants).
        cruise_speed: speed along the route (default 1.5; mpe2's full speed is 2 per axis).
        gain: proportional gain (1/s) of the approach to the landmark.
    """

    def __init__(self, env: ConstrainedSpread, *, cruise_speed: float = 1.5,
                 gain: float = 4.0) -> None:
        self.env = env
        self._follow = _WaypointFollower(env, cruise_speed=cruise_speed, gain=gain,
                                         switch=0.0)

    def reset(self, state: np.ndarray) -> None:
        lm = self.env.layout.landmark_array
        self.assignment = sorted_assignment(self.env.layout, state[:, :2])
        self._follow.start([lm[j][None] for j in self.assignment])

    def act(self, state: np.ndarray, active: np.ndarray) -> np.ndarray:
        return self._follow.act(state, active)


class ViaPointController:
    """The constrained expert: around the disc in lanes, then to the landmark, with
    start times that keep the agents apart.

    Routes: the agents are matched to landmarks in their order across the travel
    direction (:func:`sorted_assignment`); the lower half (``N // 2`` agents) passes the
    disc on the right-hand side of the travel direction, the others on the left. On each
    side the agent nearer the disc's axis takes the inner lane, at ``disc_radius +
    clearance`` from the centre, the next one a lane ``min_distance + lane_margin``
    further out, and so on. Each route runs from the start through two via-points
    abreast the disc (``disc_radius`` before and after its centre along the travel
    direction), then straight to the landmark; if one agent's straight way would pass
    closer than ``clearance`` to the disc or than ``min_distance`` to another landmark,
    every agent follows its lane until abreast of its landmark first.

    Timing: the agents do not interact physically while they keep apart, so the planner
    simulates each agent's flight alone (mpe2's physics, the same tracking law) and
    schedules start delays by prioritized planning: for each order of the agents (every
    permutation up to 4 agents; beyond, front-most first) each agent in turn gets the
    least delay (in steps, waiting at rest at its start) for which it stays at least
    ``min_distance + safety`` from every agent scheduled before it at every step (or
    halfway between ``min_distance`` and the pair's landmark spacing, if that is less:
    settled agents sit on their landmarks) and settles before the episode
    ends; the order finishing first wins. If no order works the one with the widest
    least gap is flown. Deterministic given the start state; without noise the flight
    is exactly the simulated one.

    Args:
        env: the game.
        cruise_speed: speed along the route (default 1.5).
        gain: proportional gain (1/s) of the approach to each via-point.
        clearance: margin of the inner lane from the disc (default 0.2).
        lane_margin: extra spacing of adjacent lanes beyond ``min_distance`` (0.1).
        safety: planned separation beyond ``min_distance`` (0.05).
        lane_spread: each agent's lane lies a further ``U(0, lane_spread)`` out in each
            episode, drawn from a generator seeded by the start state (so still
            deterministic given it); default 0. Experts who vary their way visit the free
            cells beside it: with one way only, the cells that a way passes by without
            entering are never demonstrated, and learners that fly a little wider
            forbid them (docs/mpe.md).
        exit_spread: each agent follows its lane a further ``U(0, exit_spread)`` past
            the disc before turning to its landmark (same generator; default 0): the
            straight legs then sweep the cells between the lane and the landmark.
    """

    def __init__(self, env: ConstrainedSpread, *, cruise_speed: float = 1.5,
                 gain: float = 4.0, clearance: float = 0.2, lane_margin: float = 0.1,
                 safety: float = 0.05, lane_spread: float = 0.0,
                 exit_spread: float = 0.0) -> None:
        self.env = env
        self.clearance = check_number("clearance", clearance)
        self.lane_spread = check_number("lane_spread", lane_spread)
        self.exit_spread = check_number("exit_spread", exit_spread)
        self.lane_margin = check_number("lane_margin", lane_margin)
        self.safety = check_number("safety", safety)
        self._kwargs = {"cruise_speed": cruise_speed, "gain": gain, "switch": 0.15}
        self._follow = _WaypointFollower(env, **self._kwargs)
        self.routes: list[np.ndarray] = []
        self.delays = np.zeros(0, dtype=np.int64)
        self.planned_gap = math.inf
        self._t = 0

    def plan_routes(self, positions: np.ndarray) -> list[np.ndarray]:
        """Each agent's via-points ``[K_i, 2]`` (the last is its landmark) from the
        starts ``[N, 2]``; sets ``assignment``, ``side``, ``lane`` and ``spread`` (each
        lane's extra offset ``[N]``)."""
        layout = self.env.layout
        n, lm = layout.n_agents, layout.landmark_array
        self.assignment = sorted_assignment(layout, positions)
        e = layout.travel_direction
        normal = np.array([-e[1], e[0]])
        centre = np.asarray(layout.disc_centre)
        order = np.argsort(positions @ normal, kind="stable")  # right-most first
        n_right = n // 2
        self.side = np.empty(n, dtype=np.int64)  # -1 right of the travel direction, +1 left
        self.lane = np.empty(n, dtype=np.int64)
        for rank, i in enumerate(order):
            if rank < n_right:
                self.side[i], self.lane[i] = -1, n_right - 1 - rank
            else:
                self.side[i], self.lane[i] = 1, rank - n_right
        r = layout.disc_radius
        self.spread, self.exit_extra = np.zeros(n), np.zeros(n)
        if self.lane_spread > 0 or self.exit_spread > 0:  # seeded by the starts
            starts = np.ascontiguousarray(positions, dtype=np.float64).tobytes()
            rng = np.random.default_rng(zlib.crc32(starts))
            self.spread = rng.uniform(0.0, self.lane_spread, n)
            self.exit_extra = rng.uniform(0.0, self.exit_spread, n)
        legs = []  # (the lane's side point, the two via-points abreast the disc, target)
        for i in range(n):
            offset = r + self.clearance + self.spread[i] + self.lane[i] * (
                layout.min_distance + self.lane_margin + self.lane_spread)
            side = centre + self.side[i] * offset * normal
            legs.append((side, [side - r * e, side + (r + self.exit_extra[i]) * e]
                         if r > 0 else [], lm[self.assignment[i]]))
        # Straight on from the lanes' exits: a constrained-optimal expert takes the
        # shortest way, and a detour (along the lane until abreast of the landmark) leaves
        # free cells unvisited that the learners then read as forbidden (docs/mpe.md).
        # Every agent detours if one straight way would pass closer than the clearance to
        # the disc or than min_distance to another landmark (where a settled agent may
        # sit): a straight descent across a lane that another agent follows is what the
        # start delays could not keep apart (3 agents).
        detour = r > 0 and any(self._needs_detour(via[-1], target, self.assignment[i])
                               for i, (_, via, target) in enumerate(legs))
        routes = []
        for side, via, target in legs:
            if detour:
                via = [*via, side + max((target - centre) @ e, r) * e]
            routes.append(np.array([*via, target]))
        return routes

    def _needs_detour(self, exit_: np.ndarray, target: np.ndarray, k: int) -> bool:
        layout = self.env.layout
        centre = np.asarray(layout.disc_centre)
        if _segment_distance(centre, exit_, target) < layout.disc_radius + self.clearance:
            return True
        others = np.delete(layout.landmark_array, k, axis=0)
        return any(_segment_distance(p, exit_, target) < layout.min_distance for p in others)

    def _fly_alone(self, start: np.ndarray, route: np.ndarray, steps: int) -> np.ndarray:
        """``[steps + 1, 2]`` positions of one agent flying ``route`` from rest at
        ``start`` with no other agent (mpe2's integration: position first, then the
        damped velocity plus the force)."""
        env = self.env
        follow = _WaypointFollower(env, **self._kwargs)
        follow.start([route])
        state = np.concatenate([start, np.zeros(2)])[None]
        out = [start.copy()]
        for _ in range(steps):
            u = follow.act(state, np.ones(1, dtype=bool)).astype(np.float64)[0]
            pos = state[0, :2] + env.dt * state[0, 2:]
            vel = (1 - env.damping) * state[0, 2:] + env.dt * env.sensitivity * u / env.mass
            speed = np.linalg.norm(vel)
            if speed > MAX_SPEED:
                vel = vel * (MAX_SPEED / speed)
            state = np.concatenate([pos, vel])[None]
            out.append(pos)
        return np.stack(out)

    def reset(self, state: np.ndarray) -> None:
        env, layout = self.env, self.env.layout
        pos = np.asarray(state, dtype=np.float64)[:, :2]
        n, horizon = layout.n_agents, env.max_steps
        self.routes = self.plan_routes(pos)
        alone = [self._fly_alone(pos[i], self.routes[i], horizon) for i in range(n)]
        lm = layout.landmark_array[self.assignment]
        spacing = np.linalg.norm(lm[:, None] - lm[None], axis=-1)
        # Settled agents sit on their landmarks, which may be closer than the margin.
        limit = np.minimum(layout.min_distance + self.safety,
                           (layout.min_distance + spacing) / 2)
        near = [np.linalg.norm(a - a[-1], axis=-1) > SUCCESS_RADIUS / 2 for a in alone]
        settle = np.array([int(np.flatnonzero(m)[-1]) + 1 if m.any() else 0 for m in near])

        def shifted(i: int, d: int) -> np.ndarray:  # waits d steps at rest, then flies
            return np.concatenate([np.repeat(pos[i][None], d, 0), alone[i][:horizon + 1 - d]])

        e = layout.travel_direction
        front = tuple(np.argsort(-(pos @ e), kind="stable").tolist())
        orders = list(itertools.permutations(range(n))) if n <= 4 else [front]
        orders.sort(key=lambda o: o != front)  # front-most first wins ties
        best: tuple[tuple[int, float], np.ndarray, float] | None = None
        for order in orders:
            delays = np.zeros(n, dtype=np.int64)
            flown: list[int] = []
            least = math.inf
            feasible = True
            for i in order:
                chosen, chosen_gap = None, -math.inf
                for d in range(horizon + 1 - settle[i]):
                    path = shifted(i, d)
                    gap = min((np.linalg.norm(path - shifted(j, delays[j]), axis=-1)
                               - limit[i, j]).min() for j in flown) if flown else math.inf
                    if gap >= 0:
                        chosen, chosen_gap = d, gap
                        break
                    if gap > chosen_gap:
                        chosen, chosen_gap = d, gap
                if chosen is None:  # cannot settle in time whatever the delay
                    chosen, chosen_gap = 0, -math.inf
                feasible &= chosen_gap >= 0 and settle[i] + chosen <= horizon
                delays[i] = chosen
                least = min(least, chosen_gap)
                flown.append(i)
            key = (0 if feasible else 1, int((settle + delays).max()) if feasible else -least)
            if best is None or key < best[0]:
                best = (key, delays, least)
        assert best is not None
        self.delays, self.planned_gap = best[1], best[2]
        self._follow.start(self.routes)
        self._t = 0

    def act(self, state: np.ndarray, active: np.ndarray) -> np.ndarray:
        v_des = self._follow.desired_velocity(state)
        v_des[self._t < self.delays] = 0.0  # waiting at the start
        self._t += 1
        return self._follow.command(state, active, v_des)


@dataclass
class Episode:
    """One flown episode.

    Attributes:
        states: ``[T+1, N, 4]`` float64 states (``x, y, vx, vy``).
        actions: ``[T, N, 2]`` float32 commands given (a frozen agent's are ignored).
        violated: ``[N]`` bool, agents that violated a constraint.
        in_disc: whether some agent entered the disc.
        too_close: whether two agents came closer than ``min_distance``.
        success: the task-success test at the end (:meth:`ConstrainedSpread.task_success`).
        covered: the landmarks were covered at the end (violations aside).
    """

    states: np.ndarray
    actions: np.ndarray
    violated: np.ndarray
    in_disc: bool
    too_close: bool
    success: bool
    covered: bool
    infos: list[dict[str, dict[str, Any]]] = field(default_factory=list, repr=False)

    @property
    def length(self) -> int:
        return len(self.actions)


def run_episode(env: ConstrainedSpread, controller: Controller, *, seed: int | None = None,
                options: dict[str, Any] | None = None) -> Episode:
    """Fly one episode of ``env`` with ``controller`` (reset with ``seed`` and
    ``options``) until every agent is done."""
    env.reset(seed=seed, options=options)
    index = {a: i for i, a in enumerate(env.possible_agents)}
    state = env.state()
    controller.reset(state)
    states, actions, infos = [state], [], []
    in_disc_any = too_close_any = False
    while env.agents:
        u = controller.act(state, env.active)
        _, _, _, _, info = env.step({a: u[index[a]] for a in env.agents})
        in_disc_any |= any(v["in_disc"] for v in info.values())
        too_close_any |= any(v["too_close"] for v in info.values())
        state = env.state()
        states.append(state)
        actions.append(u)
        infos.append(info)
    return Episode(states=np.stack(states), actions=np.stack(actions),
                   violated=env.violated.copy(), in_disc=in_disc_any,
                   too_close=too_close_any, success=env.task_success(),
                   covered=env.landmarks_covered(), infos=infos)
