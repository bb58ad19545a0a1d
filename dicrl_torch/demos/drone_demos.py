"""Expert demonstrations of the drone arena (docs/design.md §7, paper §6.2): planner and
storage (the pairs are split over learners by
:func:`~dicrl_torch.demos.partition.partition_demonstrations`; the paper's split is
:data:`PAPER_DRONE_SPLIT`).

The experts are a planner, imperfect and human-like like the paper's hand-flown Gazebo
pairs. For each pair it draws, per drone, the side on which the drone passes the central
block and then via-points at random (from an explicit ``np.random.Generator``) inside
boxes along that side, checks that the piecewise-linear path keeps a clearance from
obstacles and walls, and gives each drone a random cruise speed. Detours on both sides
put the pairs over every free cell that a straight route to the door crosses, so only
the block's cells are avoided by all pairs. One drone, drawn at random, yields: it
hovers at its first via-point until the other has passed, for the shortest wait (plus a
random hesitation) that keeps the planned drones ``SAFE_SEPARATION`` apart. A
feed-forward plus proportional velocity controller tracks the timed paths in the *true*
game (:class:`DroneArena` with its noise); only pairs in which both drones reach their
doors with no violation are kept.

A set of ``m`` pairs is ``states [m, T+1, 2, 4]`` float64 (positions and velocities),
``actions [m, T, 2, 2]`` float64 velocity commands, ``lengths [m]`` int64 (steps until
both drones were done; later entries repeat the last state, with zero actions) and the
time step ``dt``; optionally ``seeds [m]`` int64, the env seed of each pair, which makes
a pair exactly replayable (:func:`replay_pair`). On disk it is an ``.npz`` read with
``allow_pickle=False`` and checked against a schema; errors name the file, the field
and the fix (the house style of :mod:`dicrl_torch.demos.storage`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np
from numpy.typing import ArrayLike

from dicrl_torch.demos import npz
from dicrl_torch.demos.continuous import ContinuousDemonstrations
from dicrl_torch.demos.trajectories import TrajectoryArrays
from dicrl_torch.envs.drones import (
    AGENTS,
    DOORS,
    N_DRONES,
    OBSTACLES,
    ROOM_SIZE,
    DroneArena,
    DroneDynamics,
    in_own_door,
    outside_room,
)

FORMAT_VERSION = 1
ARRAY_FIELDS: tuple[str, ...] = ("states", "actions", "lengths")
SCALAR_FIELDS: tuple[str, ...] = ("dt", "format_version")
OPTIONAL_FIELDS: tuple[str, ...] = ("seeds",)
FIELDS: tuple[str, ...] = ARRAY_FIELDS + SCALAR_FIELDS
PAPER_DRONE_SPLIT: tuple[int, ...] = (4, 5)
"""The paper's split of the 9 pairs over two learners."""

# ---- planner constants (metres, seconds) -------------------------------------------
CLEARANCE: float = 0.35
"""Least distance of a planned path from obstacles and walls (doors excepted)."""
SAFE_SEPARATION: float = 1.0
"""Least planned distance between the drones (twice the collision radius), so that
tracking errors and noise never bring them within ``PROXIMITY_RADIUS``."""
CRUISE_SPEED: tuple[float, float] = (1.0, 1.2)
"""Range of each drone's cruise speed along its path (m/s), below ``max_speed`` so
the controller keeps headroom to correct tracking errors. Demonstrations at 0.6-0.85 m/s
made the learned reward weights shrink to match them (a policy too slow to reach the
door in an episode; docs/drones.md, "Beside the paper, and what decides SR")."""
HESITATION: tuple[float, float] = (0.0, 0.3)
"""Range of the extra wait (s) of the yielding drone, on top of the shortest safe one."""
KP: float = 1.5
"""Proportional gain (1/s) of the tracking controller."""
Box = tuple[tuple[float, float], tuple[float, float]]
_DOOR_APPROACH: Box = ((7.3, 9.4), (8.9, 9.3))  # below the door, anywhere across it
VIA_BOXES: dict[str, tuple[Box, ...]] = {
    # Pass the block on the side of the own door (under it first).
    "far": (
        ((2.3, 3.0), (2.2, 3.0)),    # on the straight route: the yielding drone hovers here
        ((4.0, 4.6), (4.3, 4.6)),    # under the block's near half
        ((6.4, 6.7), (4.3, 4.6)),    # beyond its lower far corner
        ((6.4, 6.7), (6.4, 6.7)),    # beyond its upper far corner
        _DOOR_APPROACH,
    ),
    # Pass the block on the side of the own start (over it last).
    "near": (
        ((1.9, 2.6), (2.2, 3.0)),    # the yielding drone hovers here
        ((3.3, 3.6), (5.0, 5.6)),    # beside the block's near side
        ((3.3, 3.6), (6.4, 6.6)),    # beyond its upper near corner
        ((4.8, 5.6), (6.4, 6.7)),    # above the block
        _DOOR_APPROACH,
    ),
}
"""``((x_lo, x_hi), (y_lo, y_hi))`` boxes of drone 0's via-points, in path order, for
each side of the central block; drone 1 uses their mirror image ``x -> ROOM_SIZE - x``.
The path ends in the door, at ``y = ROOM_SIZE - 0.05`` and an ``x`` drawn uniformly
across the door's span less ``DOOR_MARGIN`` at each end, so that the pairs enter the
door anywhere across it."""
DOOR_MARGIN: float = 0.3
_HOLD_WAYPOINT = 1  # index in the waypoint list (0 is the start): the first via-point
_MAX_WAIT_S = 12.0
_WAIT_STEP_S = 0.25


# ====================================================================== data + schema
def _check_float_array(a: np.ndarray, field: str, source: str) -> None:
    npz.check_float_dtype(a, field, source)
    npz.refuse_first(~np.isfinite(a), lambda *idx: (
        f"{source}: field '{field}' holds a NaN or inf at index {idx}; "
        f"demonstrations must be finite. Regenerate them."))


def validate_drone_arrays(
    states: ArrayLike, actions: ArrayLike, lengths: ArrayLike, dt: float,
    seeds: ArrayLike | None = None, *, source: str,
) -> None:
    """Check drone demonstration arrays against the schema; raise ``ValueError`` if not.

    Args:
        states: ``[m, T+1, 2, 4]`` float positions (in the room ``[0, 10]^2``) and
            velocities.
        actions: ``[m, T, 2, 2]`` float velocity commands in ``[-1, 1]``.
        lengths: ``[m]`` int in ``[1, T]``: steps until both drones were done; after
            it the states repeat and the actions are 0.
        dt: positive time step in seconds.
        seeds: None or ``[m]`` non-negative int env seeds.
        source: what the arrays came from, put at the start of every error message.

    Raises:
        ValueError: naming ``source``, the offending field and the fix.
    """
    if isinstance(dt, bool | np.bool_) or not isinstance(dt, int | float | np.number) \
            or not np.isfinite(dt) or dt <= 0:
        raise ValueError(f"{source}: field 'dt' must be a positive finite float, got {dt!r}.")
    states, actions, lengths = np.asarray(states), np.asarray(actions), np.asarray(lengths)
    _check_float_array(states, "states", source)
    _check_float_array(actions, "actions", source)
    if states.ndim != 4 or states.shape[2:] != (N_DRONES, 4) or states.shape[0] == 0 \
            or states.shape[1] < 2:
        raise ValueError(
            f"{source}: field 'states' must have shape [m, T+1, {N_DRONES}, 4] with m >= 1 "
            f"and T >= 1, got shape {states.shape}."
        )
    m, t1 = states.shape[:2]
    if actions.shape != (m, t1 - 1, N_DRONES, 2):
        raise ValueError(
            f"{source}: field 'actions' has shape {actions.shape}, but states "
            f"{states.shape} = [m, T+1, {N_DRONES}, 4] requires actions of shape "
            f"{(m, t1 - 1, N_DRONES, 2)} = [m, T, {N_DRONES}, 2]."
        )
    npz.check_lengths(lengths, m, t1 - 1, source, "pair")
    pos = states[..., :2]
    npz.refuse_first(outside_room(pos), lambda k, t, i: (  # [m, T+1, 2]
        f"{source}: field 'states' puts drone {i} at {pos[k, t, i].tolist()} (pair {k}, "
        f"time {t}), outside the room [0, {ROOM_SIZE}]^2; expert demonstrations never "
        f"leave the room. Regenerate them."))
    npz.refuse_first(np.abs(actions) > 1.0, lambda k, t, i, c: (
        f"{source}: field 'actions' holds {actions[k, t, i, c]} (pair {k}, time {t}, "
        f"drone {i}), outside the command range [-1, 1]; clip or regenerate it."))
    for k, n in enumerate(lengths.tolist()):
        if not (np.all(states[k, n + 1:] == states[k, n]) and np.all(actions[k, n:] == 0)):
            raise ValueError(
                f"{source}: field 'lengths' says pair {k} ends after {n} steps, but its "
                f"states change or its actions are non-zero later; the lengths do not "
                f"match the trajectories. Regenerate the demonstrations."
            )
    npz.check_seeds(seeds, m, source, "pair")


@dataclass(frozen=True, eq=False, repr=False)
class DroneDemonstrations(TrajectoryArrays):
    """Demonstrated pairs of drone trajectories, validated on construction (a
    :class:`~dicrl_torch.demos.trajectories.Trajectories` whose trajectories are the
    pairs; equal by content).

    The arrays are copied read-only (float64, int64), so the object is immutable.

    Args:
        states: ``[m, T+1, 2, 4]`` positions ``(x, y)`` and velocities ``(vx, vy)``.
        actions: ``[m, T, 2, 2]`` velocity commands in ``[-1, 1]`` (0 once done).
        lengths: ``[m]`` steps until both drones of a pair were done.
        dt: time step in seconds.
        seeds: optional ``[m]`` env seeds, for an exact replay with :func:`replay_pair`.
    """

    states: np.ndarray
    actions: np.ndarray
    lengths: np.ndarray
    dt: float
    seeds: np.ndarray | None = None

    per_trajectory: ClassVar[tuple[str, ...]] = ("states", "actions", "lengths", "seeds")
    unit: ClassVar[str] = "pairs"

    def __post_init__(self) -> None:
        validate_drone_arrays(self.states, self.actions, self.lengths, self.dt, self.seeds,
                              source="DroneDemonstrations")
        object.__setattr__(self, "states", npz.frozen(self.states, np.float64))
        object.__setattr__(self, "actions", npz.frozen(self.actions, np.float64))
        object.__setattr__(self, "lengths", npz.frozen(self.lengths, np.int64))
        object.__setattr__(self, "dt", float(self.dt))
        if self.seeds is not None:
            object.__setattr__(self, "seeds", npz.frozen(self.seeds, np.int64))

    @property
    def n_pairs(self) -> int:
        """``m``, the number of pairs (:attr:`n_trajectories`)."""
        return self.n_trajectories

    def drone_lengths(self) -> np.ndarray:
        """``[m, 2]`` int64: the step at which each drone reached its door (its last
        state); ``lengths`` where it did not."""
        at = in_own_door(self.states[:, 1:, :, :2])  # [m, T, 2]
        first = np.where(at.any(1), at.argmax(1) + 1, self.lengths[:, None])
        return np.minimum(first, self.lengths[:, None]).astype(np.int64)

    def to_continuous(self) -> ContinuousDemonstrations:
        """The same pairs as generic continuous demonstrations (what solvers and
        feature sums of any continuous game read): ``states [m, T+1, 2, 4]``,
        ``actions [m, T, 2, 2]``, ``lengths``, the seeds, the agent names of the arena
        and, as ``agent_lengths``, :meth:`drone_lengths` (a drone's commands after it
        reached its door are ignored by the env, so they are not its choices)."""
        return ContinuousDemonstrations(
            states=self.states, actions=self.actions, lengths=self.lengths,
            agent_names=AGENTS, seeds=self.seeds, agent_lengths=self.drone_lengths())

    def __repr__(self) -> str:
        return f"DroneDemonstrations(m={self.n_pairs}, T={self.horizon}, dt={self.dt})"


# ================================================================================ disk
def _archive_fields(demos: DroneDemonstrations) -> dict[str, np.ndarray | None]:
    return {"states": demos.states, "actions": demos.actions, "lengths": demos.lengths,
            "dt": np.float64(demos.dt), "format_version": np.int64(FORMAT_VERSION),
            "seeds": demos.seeds}


def save_drone_demonstrations(
    path: str | os.PathLike[str], demos: DroneDemonstrations
) -> Path:
    """Write ``demos`` to ``path`` for :func:`load_drone_demonstrations`: a compressed
    ``.npz``, written atomically by :func:`~dicrl_torch.demos.npz.save_archive` (no
    suffix is appended, parent directories are created); return the path."""
    return npz.save_archive(path, demos, DroneDemonstrations, fields=_archive_fields,
                            writer="save_drone_demonstrations",
                            how="build one with make_drone_demonstrations(...)")


def load_drone_demonstrations(
    path: str | os.PathLike[str], *, n_pairs: int | None = None, dt: float | None = None,
) -> DroneDemonstrations:
    """Read demonstrations written by :func:`save_drone_demonstrations`, never unpickling.

    Args:
        path: the ``.npz`` file.
        n_pairs, dt: when given, the file must hold exactly this many pairs / this
            time step.

    Returns:
        The validated demonstrations.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: the file is not a valid drone demonstrations archive or does not
            match the expectation; the message names the file, the field and the fix.
    """
    path = Path(path)
    source = f"drone demonstrations file '{path}'"
    fix = "save_drone_demonstrations"
    with npz.open_archive(path, source=source, required=FIELDS, optional=OPTIONAL_FIELDS,
                          version=FORMAT_VERSION, fix=fix,
                          generate="Generate the demonstrations with "
                                   "make_drone_demonstrations first") as archive:
        file_dt = npz.read_scalar(archive, "dt", source, fix, kind=float)
        arrays = {f: npz.read_field(archive, f, source, fix) for f in ARRAY_FIELDS}
        seeds = (npz.read_field(archive, "seeds", source, fix) if "seeds" in archive.files
                 else None)
    validate_drone_arrays(arrays["states"], arrays["actions"], arrays["lengths"], file_dt,
                          seeds, source=source)
    npz.check_expected(source, {"n_pairs": arrays["states"].shape[0], "dt": file_dt},
                       {"n_pairs": n_pairs, "dt": dt})
    return DroneDemonstrations(dt=file_dt, seeds=seeds, **arrays)


# ============================================================================ planner
@dataclass(frozen=True)
class TimedPath:
    """A piecewise-linear path flown at constant speed with one hover.

    Args:
        waypoints: ``[K, 2]`` positions, the first one the start.
        speed: cruise speed (m/s).
        hold_index: the waypoint at which the drone hovers.
        hold_s: how long it hovers (s).
    """

    waypoints: np.ndarray
    speed: float
    hold_index: int = 0
    hold_s: float = 0.0

    @property
    def _arc(self) -> np.ndarray:
        seg = np.linalg.norm(np.diff(self.waypoints, axis=0), axis=1)
        return np.concatenate([[0.0], np.cumsum(seg)])

    def _s(self, t: np.ndarray) -> np.ndarray:
        arc = self._arc
        t_hold = arc[self.hold_index] / self.speed
        s = self.speed * (np.minimum(t, t_hold) + np.maximum(0.0, t - t_hold - self.hold_s))
        return np.clip(s, 0.0, arc[-1])

    def position(self, t: ArrayLike) -> np.ndarray:
        """``[..., 2]`` planned positions at times ``t [...]`` (s)."""
        t = np.asarray(t, dtype=np.float64)
        s, arc, w = self._s(t), self._arc, self.waypoints
        return np.stack([np.interp(s, arc, w[:, 0]), np.interp(s, arc, w[:, 1])], -1)

    def velocity(self, t: ArrayLike) -> np.ndarray:
        """``[..., 2]`` planned velocities at times ``t [...]`` (0 hovering or at the end)."""
        t = np.asarray(t, dtype=np.float64)
        arc = self._arc
        s = self._s(t)
        seg = np.clip(np.searchsorted(arc, s, side="right") - 1, 0, len(arc) - 2)
        d = np.diff(self.waypoints, axis=0)
        unit = d / np.linalg.norm(d, axis=1, keepdims=True)
        t_hold = arc[self.hold_index] / self.speed
        moving = (s < arc[-1]) & ~((t >= t_hold) & (t < t_hold + self.hold_s))
        return unit[seg] * (self.speed * moving)[..., None]

    @property
    def duration(self) -> float:
        """Time (s) at which the planned drone arrives."""
        return self._arc[-1] / self.speed + self.hold_s


def _box_distance(p: np.ndarray) -> np.ndarray:
    """``[P]`` distance of points ``[P, 2]`` to the nearest obstacle (0 inside)."""
    o = np.asarray(OBSTACLES)
    dx = np.maximum(np.maximum(o[:, 0] - p[:, :1], 0.0), p[:, :1] - o[:, 2])
    dy = np.maximum(np.maximum(o[:, 1] - p[:, 1:], 0.0), p[:, 1:] - o[:, 3])
    return np.hypot(dx, dy).min(1)


def path_clearance(waypoints: np.ndarray, drone: int, step: float = 0.05) -> float:
    """Least distance (m) of the polyline ``waypoints [K, 2]`` from obstacles and walls;
    the top wall is ignored inside drone ``drone``'s door span (shrunk by 0.2 m)."""
    pts = [waypoints[:1]]
    for a, b in zip(waypoints[:-1], waypoints[1:], strict=True):
        n = max(2, int(np.ceil(np.linalg.norm(b - a) / step)) + 1)
        pts.append(a + np.linspace(0.0, 1.0, n)[1:, None] * (b - a))
    p = np.concatenate(pts)
    lo, hi = DOORS[drone]
    in_door = (p[:, 0] >= lo + 0.2) & (p[:, 0] <= hi - 0.2)
    top = np.where(in_door, np.inf, ROOM_SIZE - p[:, 1])
    walls = np.minimum.reduce([p[:, 0], ROOM_SIZE - p[:, 0], p[:, 1], top])
    return float(np.minimum(walls, _box_distance(p)).min())


def _sample_route(drone: int, start: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """``[7, 2]`` waypoints: start, 5 random via-points on a random side of the central
    block, the door; mirrored for drone 1."""
    side = ("far", "near")[int(rng.integers(2))]
    via = np.array([[rng.uniform(*bx), rng.uniform(*by)] for bx, by in VIA_BOXES[side]])
    lo, hi = DOORS[0]  # drone 0's door: drone 1's route is the mirror image (below)
    end_x = rng.uniform(lo + DOOR_MARGIN, hi - DOOR_MARGIN)
    end = np.array([[end_x, ROOM_SIZE - 0.05]])
    pts = np.concatenate([via, end])
    if drone == 1:
        pts[:, 0] = ROOM_SIZE - pts[:, 0]
    return np.concatenate([start[None], pts])


def plan_pair(
    starts: np.ndarray, rng: np.random.Generator, *, dt: float = 0.1,
) -> tuple[TimedPath, TimedPath] | None:
    """Plan timed paths for both drones from ``starts [2, 2]``; None when the drawn
    via-points give no safe plan (the caller redraws).

    Returns:
        One :class:`TimedPath` per drone.
    """
    routes = [_sample_route(i, starts[i], rng) for i in range(N_DRONES)]
    if min(path_clearance(r, i) for i, r in enumerate(routes)) < CLEARANCE:
        return None
    speeds = rng.uniform(*CRUISE_SPEED, size=N_DRONES)
    yielder = int(rng.integers(N_DRONES))
    wait = float(rng.uniform(*HESITATION))
    while wait <= _MAX_WAIT_S:
        paths = [TimedPath(routes[i], float(speeds[i]), _HOLD_WAYPOINT,
                           wait if i == yielder else 0.0) for i in range(N_DRONES)]
        t = np.arange(0.0, min(p.duration for p in paths) + dt, dt)
        gap = np.linalg.norm(paths[0].position(t) - paths[1].position(t), axis=-1)
        if gap.min() >= SAFE_SEPARATION:
            return paths[0], paths[1]
        wait += _WAIT_STEP_S
    return None


def track(path: TimedPath, t: float, state: np.ndarray, dynamics: DroneDynamics) -> np.ndarray:
    """``[2]`` velocity command in ``[-1, 1]`` following ``path`` at time ``t``.

    Feed-forward of the planned velocity one time constant ahead (so the first-order
    lag does not make the drone cut corners late) plus a proportional pull towards the
    planned position.

    Args:
        path: the timed path.
        t: time since the start (s).
        state: ``[4]`` position and velocity.
        dynamics: the drone dynamics (for ``tau`` and ``max_speed``).
    """
    v = path.velocity(t + dynamics.tau) + KP * (path.position(t) - state[:2])
    # The command as the dynamics fly it, so a demonstrated action is the one applied.
    return dynamics.bound(v / dynamics.max_speed)


def fly_pair(
    paths: tuple[TimedPath, TimedPath], env: DroneArena, seed: int,
) -> tuple[np.ndarray, np.ndarray, bool]:
    """Track ``paths`` in ``env`` reset with ``seed`` (whose starts the paths must use).

    Returns:
        ``states [L+1, 2, 4]``, ``actions [L, 2, 2]`` (0 for done drones) and whether
        both drones reached their doors without a violation.
    """
    env.reset(seed=seed)
    states, actions = [env.state()], []
    while env.agents:
        t = env.timestep * env.dynamics.dt
        s = env.state()
        cmd = np.zeros((N_DRONES, 2))
        for a in env.agents:
            i = AGENTS.index(a)
            cmd[i] = track(paths[i], t, s[i], env.dynamics)
        env.step({a: cmd[AGENTS.index(a)] for a in env.agents})
        states.append(env.state())
        actions.append(cmd)
    ok = bool(env.reached.all() and not env.violated.any())
    return np.stack(states), np.stack(actions), ok


def make_drone_demonstrations(
    n_pairs: int = 9,
    *,
    rng: np.random.Generator,
    dynamics: DroneDynamics | None = None,
    max_steps: int = 300,
    max_attempts: int | None = None,
) -> DroneDemonstrations:
    """Plan and fly ``n_pairs`` successful demonstration pairs in the true game.

    Args:
        n_pairs: number of pairs ``m`` (9 in the paper).
        rng: the only source of randomness: via-points, speeds, yielding, env seeds.
        dynamics: the drone dynamics (default :class:`DroneDynamics()`).
        max_steps: episode limit of the env the pairs are flown in.
        max_attempts: how many plans to try in all (default ``20 * n_pairs``).

    Returns:
        The demonstrations, padded to the longest pair, with their env seeds.

    Raises:
        RuntimeError: fewer than ``n_pairs`` successful pairs in ``max_attempts``.
    """
    if not npz.is_int(n_pairs) or n_pairs < 1:
        raise ValueError(f"n_pairs must be a positive int, got {n_pairs!r}.")
    if not isinstance(rng, np.random.Generator):
        raise TypeError(
            f"rng must be a numpy.random.Generator, got {type(rng).__name__}; pass "
            f"np.random.default_rng(seed)."
        )
    max_attempts = 20 * n_pairs if max_attempts is None else max_attempts
    env = DroneArena(constrained=True, max_steps=max_steps, dynamics=dynamics)
    pairs: list[tuple[np.ndarray, np.ndarray, int]] = []
    attempts = 0
    while len(pairs) < n_pairs:
        if attempts >= max_attempts:
            raise RuntimeError(
                f"Only {len(pairs)} of {n_pairs} drone demonstration pairs succeeded in "
                f"{max_attempts} attempts; raise max_steps or max_attempts, or lower the "
                f"dynamics' noise_std."
            )
        attempts += 1
        seed = int(rng.integers(2**31 - 1))
        env.reset(seed=seed)
        plan = plan_pair(env.state()[:, :2], rng, dt=env.dynamics.dt)
        if plan is None:
            continue
        states, actions, ok = fly_pair(plan, env, seed)
        if ok:
            pairs.append((states, actions, seed))
    S, A, lengths = npz.pad_episodes([(s, a) for s, a, _ in pairs])
    return DroneDemonstrations(states=S, actions=A, lengths=lengths, dt=env.dynamics.dt,
                               seeds=np.array([sd for _, _, sd in pairs], dtype=np.int64))


def replay_pair(
    demos: DroneDemonstrations, k: int, *, constrained: bool = True,
    dynamics: DroneDynamics | None = None, max_steps: int = 300,
) -> tuple[np.ndarray, DroneArena]:
    """Re-fly pair ``k``'s recorded actions in a fresh env reset with its seed.

    Returns:
        ``states [lengths[k]+1, 2, 4]`` and the env (for ``reached``/``violated``).
    """
    if demos.seeds is None:
        raise ValueError("These demonstrations carry no seeds; an exact replay needs them.")
    env = DroneArena(constrained=constrained, max_steps=max_steps, dynamics=dynamics)
    env.reset(seed=int(demos.seeds[k]))
    states = [env.state()]
    for t in range(int(demos.lengths[k])):
        if not env.agents:
            break
        env.step({a: demos.actions[k, t, AGENTS.index(a)] for a in env.agents})
        states.append(env.state())
    return np.stack(states), env
