"""The drone arena as a PettingZoo ``ParallelEnv`` (:class:`DroneArena`) and as one
gymnasium agent flying both drones (:class:`JointDroneEnv`, the joint env the SAC solver
drives), with the joint observations' conversions to and from joint states
(:mod:`dicrl_torch.envs.drones`)."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces

from dicrl_torch.checks import check_positive, setting_int
from dicrl_torch.envs.drones.arrays import is_torch
from dicrl_torch.envs.drones.dynamics import DroneDynamics, joint_step
from dicrl_torch.envs.drones.geometry import (
    AGENTS,
    N_DRONES,
    NOMINAL_STARTS,
    OBSTACLES,
    PROXIMITY_RADIUS,
    ROOM_SIZE,
    START_JITTER,
    door_centres,
    in_obstacle,
    in_own_door,
    outside_room,
    too_close,
)
from dicrl_torch.envs.drones.render import constraint_cell_mask, render_arena
from dicrl_torch.envs.parallel import CheckedParallelEnv
from dicrl_torch.envs.planar import PlanarCommandSpaces

if TYPE_CHECKING:  # vector.py builds on this module
    from dicrl_torch.envs.drones.vector import DroneVectorEnv


class DroneArena(PlanarCommandSpaces, CheckedParallelEnv):
    """Two drones crossing a 10 m room; the true game or its nominal game.

    Observation of drone ``i`` (float32, 10 values): own position and velocity, the
    other drone's position and velocity, own door centre. Action: ``[2]`` float32
    velocity command in ``[-1, 1]^2``. Reward: 1 in the step a drone reaches its door
    without a violation, else 0 (the learner brings its own reward; docs/design.md §7).

    ``infos[agent]`` has ``violated``, ``reached``, ``collision`` (this step),
    ``in_obstacle`` and ``position`` (``[2]`` float64). An agent leaves
    ``agents`` (terminated) when it reaches its door or, in the true game, violates; all
    are truncated after ``max_steps``. The random stream (start jitter, noise) depends
    only on the seed: every step draws noise for both drones, flying or not.

    Args:
        constrained: True for the true game (violators freeze), False for the nominal.
        max_steps: episode limit in steps (default 300, i.e. 30 s at dt = 0.1).
        dynamics: the drone dynamics (default :class:`DroneDynamics()`).
        proximity_radius: collision distance in metres.
        render_mode: None or ``"rgb_array"``.
    """

    metadata = {"render_modes": ["rgb_array"], "name": "drone_arena_v0",
                "is_parallelizable": True, "render_fps": 10}

    def __init__(
        self,
        *,
        constrained: bool = True,
        max_steps: int = 300,
        dynamics: DroneDynamics | None = None,
        proximity_radius: float = PROXIMITY_RADIUS,
        render_mode: str | None = None,
    ) -> None:
        if not isinstance(constrained, bool | np.bool_):
            raise ValueError(
                f"constrained must be a bool (True: true game, False: nominal game), "
                f"got {constrained!r}."
            )
        setting_int("max_steps", max_steps, example=300, why="episode limit in steps")
        if dynamics is None:
            dynamics = DroneDynamics()
        if not isinstance(dynamics, DroneDynamics):
            raise ValueError(
                f"dynamics must be a DroneDynamics, got {type(dynamics).__name__}; build "
                f"one with DroneDynamics(dt=..., tau=...)."
            )
        self._check_render_mode(render_mode)
        self.constrained = bool(constrained)
        self.max_steps = int(max_steps)
        self.dynamics = dynamics
        self.proximity_radius = check_positive("proximity_radius", proximity_radius)
        self.render_mode = render_mode
        self.possible_agents = list(AGENTS)
        self._index = {a: i for i, a in enumerate(self.possible_agents)}
        v = dynamics.vel_limit
        lo, hi = 0.0, ROOM_SIZE
        self._obs_low = np.array([lo, lo, -v, -v] * 2 + [0.0, 0.0], dtype=np.float32)
        self._obs_high = np.array([hi, hi, v, v] * 2 + [ROOM_SIZE] * 2, dtype=np.float32)
        self.state_space = spaces.Box(
            low=np.tile(np.array([lo, lo, -v, -v]), (N_DRONES, 1)),
            high=np.tile(np.array([hi, hi, v, v]), (N_DRONES, 1)), dtype=np.float64,
        )
        self._doors = door_centres()

        self.agents: list[str] = []
        self.timestep = 0
        self._state: np.ndarray | None = None  # [N, 4] float64
        self._active = np.zeros(N_DRONES, dtype=bool)
        self.violated = np.zeros(N_DRONES, dtype=bool)  # ever violated, this episode
        self.reached = np.zeros(N_DRONES, dtype=bool)  # reached the door, this episode
        self._history: list[np.ndarray] = []  # positions [N, 2] per time step
        self._overlay: np.ndarray | None = None
        self._rng: np.random.Generator | None = None

    # ---- episode ------------------------------------------------------------------
    @property
    def started(self) -> bool:
        return self._state is not None

    def _reset(self, options: dict[str, Any] | None
               ) -> tuple[dict[str, np.ndarray], dict[str, dict[str, Any]]]:
        """``reset(options={"positions": [[x0, y0], [x1, y1]]})`` sets the start positions
        instead of the jittered nominal ones (other keys are ignored)."""
        jitter = self._rng.uniform(-START_JITTER, START_JITTER, size=(N_DRONES, 2))
        pos = np.asarray(NOMINAL_STARTS, dtype=np.float64) + jitter
        if options and options.get("positions") is not None:
            pos = _check_start_positions(options["positions"])
        self._state = np.concatenate([pos, np.zeros((N_DRONES, 2))], axis=1)
        self._active = np.ones(N_DRONES, dtype=bool)
        self.violated = np.zeros(N_DRONES, dtype=bool)
        self.reached = np.zeros(N_DRONES, dtype=bool)
        self.timestep = 0
        self._history = [pos.copy()]
        self.agents = list(self.possible_agents)
        obs = {a: self.observe(a) for a in self.agents}
        infos = {a: self._info(i, False, False, False, False)
                 for a, i in self._index.items()}
        return obs, infos

    def _step(self, given: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        """The step of :meth:`CheckedParallelEnv.step`; ``given`` holds a ``[2]`` velocity
        command for every live agent."""
        live = list(given)
        command = np.zeros((N_DRONES, 2))
        for agent, a in given.items():
            command[self._index[agent]] = self._check_command(agent, a)
        noise = self.dynamics.sample_noise(self._rng, (N_DRONES, 2))
        res = joint_step(self._state, command, self._active, noise, dynamics=self.dynamics,
                         proximity_radius=self.proximity_radius, constrained=self.constrained)
        self._state, self._active = res.state, res.active
        self.violated |= res.violated
        self.reached |= res.reached
        self.timestep += 1
        self._history.append(self._state[:, :2].copy())

        obs, rewards, terms, truncs, infos = {}, {}, {}, {}, {}
        for a in live:
            i = self._index[a]
            obs[a] = self.observe(a)
            rewards[a] = float(res.reached[i] and not self.violated[i])
            terms[a] = not bool(res.active[i])
            truncs[a] = not terms[a] and self.timestep >= self.max_steps
            infos[a] = self._info(i, bool(res.violated[i]), bool(res.reached[i]),
                                  bool(res.collision), bool(res.in_obstacle[i]))
        self.agents = [a for a in live if not (terms[a] or truncs[a])]
        return obs, rewards, terms, truncs, infos

    def observe(self, agent: str) -> np.ndarray:
        """``[10]`` float32 observation of ``agent`` (also for agents that are done)."""
        i = self._agent_index(agent)
        self._require_started("observe")
        j = 1 - i
        o = np.concatenate([self._state[i], self._state[j], self._doors[i]])
        return self._bounded(o)  # the dynamics keep o inside the bounds

    def state(self) -> np.ndarray:
        """``[N, 4]`` float64 positions and velocities (done drones where they stopped)."""
        self._require_started("state")
        return self._state.copy()

    @property
    def active(self) -> np.ndarray:
        """``[N]`` bool: drones still flying."""
        return self._active.copy()

    def trajectory(self) -> np.ndarray:
        """``[t+1, N, 2]`` float64 positions since the last reset."""
        return np.stack(self._history) if self._history else np.zeros((0, N_DRONES, 2))

    # ---- rendering ----------------------------------------------------------------
    def set_constraint_overlay(self, cells: Any) -> None:
        """Cells to draw as (learned) constraints in :meth:`render`; see
        :func:`render_arena` for the accepted forms. ``None`` clears the overlay."""
        self._overlay = None if cells is None else constraint_cell_mask(cells)

    def _render(self) -> np.ndarray:
        title = f"{self.metadata['name']}  t={self.timestep}/{self.max_steps}" + (
            "" if self.constrained else "  (nominal)")
        traj = self.trajectory() if self._history else None
        return render_arena(
            trajectories=None if traj is None else [traj],
            positions=None if self._state is None else self._state[:, :2],
            frozen=self.violated & ~self._active if self.constrained else None,
            constraint_cells=self._overlay, proximity_radius=self.proximity_radius,
            title=title,
        )

    # ---- helpers ------------------------------------------------------------------
    def _info(self, i: int, violated: bool, reached: bool, collision: bool,
              obstacle: bool) -> dict[str, Any]:
        return {"violated": violated, "reached": reached, "collision": collision,
                "in_obstacle": obstacle, "position": self._state[i, :2].copy()}

    def _check_command(self, agent: str, a: Any) -> np.ndarray:
        """``a`` as a ``[2]`` float64 command, clipped to ``[-1, 1]``."""
        arr = np.asarray(a, dtype=np.float64) if _is_numeric(a) else None
        if arr is None or arr.shape != (2,) or not np.all(np.isfinite(arr)):
            raise ValueError(
                f"Action of {agent} must be a finite [2] velocity command in [-1, 1], "
                f"got {a!r}."
            )
        return np.clip(arr, -1.0, 1.0)


def _is_numeric(a: Any) -> bool:
    try:
        arr = np.asarray(a)
    except (TypeError, ValueError):
        return False
    return np.issubdtype(arr.dtype, np.number) and not np.issubdtype(arr.dtype, np.complexfloating)


def _check_start_positions(positions: Any) -> np.ndarray:
    pos = np.asarray(positions, dtype=np.float64) if _is_numeric(positions) else None
    if pos is None or pos.shape != (N_DRONES, 2) or not np.all(np.isfinite(pos)):
        raise ValueError(
            f"options['positions'] must be finite [{N_DRONES}, 2] start positions (x, y) in "
            f"metres, got {positions!r}."
        )
    bad = outside_room(pos) | in_obstacle(pos) | in_own_door(pos)
    if bad.any() or too_close(pos):
        raise ValueError(
            f"options['positions'] {pos.tolist()} must lie in the room, outside the "
            f"obstacles {list(OBSTACLES)} and the doors, and {PROXIMITY_RADIUS} m apart."
        )
    return pos


# ------------------------------------------------------------------ joint gym adapter
RewardFn = Callable[[np.ndarray, np.ndarray, np.ndarray], float]


def joint_obs_to_state(obs: Any) -> Any:
    """Joint observations ``[..., 20]`` of :class:`JointDroneEnv` to states ``[..., 2, 4]``
    (drone ``i``'s own position and velocity are its observation's first 4 values)."""
    obs_dim = obs.shape[-1] // N_DRONES
    parts = [obs[..., i * obs_dim:i * obs_dim + 4] for i in range(N_DRONES)]
    return torch.stack(parts, -2) if is_torch(obs) else np.stack(parts, -2)


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
    if s.ndim < 2 or s.shape[-2:] != (N_DRONES, 4):
        raise ValueError(f"states must have shape [..., {N_DRONES}, 4], got {list(s.shape)}.")
    doors = door_centres()
    parts = []
    for i in range(N_DRONES):
        door = np.broadcast_to(doors[i], (*s.shape[:-2], 2))
        parts.append(np.concatenate([s[..., i, :], s[..., 1 - i, :], door], -1))
    return np.concatenate(parts, -1).astype(np.float32)


class JointDroneEnv(gym.Env):
    """Both drones as one gymnasium agent, for single-policy solvers (e.g. SB3 SAC).

    Observation: ``[20]`` float32, drone 0's observation then drone 1's. Action:
    ``[4]`` float32 in ``[-1, 1]``, drone 0's command then drone 1's (a done drone's
    part is ignored). Reward: ``reward_fn(obs, action, next_obs)`` or 0. Terminated
    when no drone flies any more (all arrived or frozen); truncated at ``max_steps``.
    ``info`` holds per-drone ``[2]`` bool arrays ``violated``, ``reached``, ``active``,
    ``in_obstacle``, the bool ``collision`` and the ``[2, 4]`` float64
    ``state``.

    It is a joint env as the constrained SAC solver drives one (the protocol of
    :mod:`dicrl_torch.solvers.sac`): :attr:`n_agents`, :attr:`state_shape`, the infos
    above, :meth:`obs_from_states` and :meth:`set_rng`; build it for the solver with
    ``functools.partial(JointDroneEnv, max_steps=...)`` (the solver adds
    ``constrained``).

    Args:
        reward_fn: ``(obs [20], action [4], next_obs [20]) -> float``, e.g. a learner's
            linear reward on :func:`joint_obs_to_state` features; None gives 0.
        **arena_kwargs: forwarded to :class:`DroneArena` (``constrained``,
            ``max_steps``, ``dynamics``, ``proximity_radius``, ``render_mode``).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}
    n_agents: int = N_DRONES
    state_shape: tuple[int, int] = (N_DRONES, 4)
    """``(N, d_s)`` of ``info["state"]``: per drone ``x, y, vx, vy``."""

    def __init__(self, *, reward_fn: RewardFn | None = None, **arena_kwargs: Any) -> None:
        if reward_fn is not None and not callable(reward_fn):
            raise ValueError(
                f"reward_fn must be callable (obs, action, next_obs) -> float or None, got "
                f"{type(reward_fn).__name__}."
            )
        self.arena = DroneArena(**arena_kwargs)
        self.reward_fn = reward_fn
        self.render_mode = self.arena.render_mode
        single = self.arena.observation_space(AGENTS[0])
        self.observation_space = spaces.Box(
            low=np.tile(single.low, N_DRONES), high=np.tile(single.high, N_DRONES),
            dtype=np.float32,
        )
        self.action_space = spaces.Box(low=-1.0, high=1.0, shape=(2 * N_DRONES,),
                                       dtype=np.float32)
        self._obs: np.ndarray | None = None

    def _joint_obs(self) -> np.ndarray:
        return np.concatenate([self.arena.observe(a) for a in AGENTS])

    def _joint_info(self, infos: dict[str, dict[str, Any]]) -> dict[str, Any]:
        def per(key: str) -> np.ndarray:
            return np.array([bool(infos.get(a, {}).get(key, False)) for a in AGENTS])

        return {"violated": per("violated"), "reached": per("reached"),
                "in_obstacle": per("in_obstacle"),
                "collision": bool(per("collision").any()), "active": self.arena.active,
                "state": self.arena.state()}

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        _, infos = self.arena.reset(seed=seed, options=options)
        self._obs = self._joint_obs()
        return self._obs.copy(), self._joint_info(infos)

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if self._obs is None:
            raise RuntimeError("step() called before reset(); call env.reset(seed=...) first.")
        if not self.arena.agents:
            raise RuntimeError("The episode is over; call env.reset() before step().")
        arr = np.asarray(action, dtype=np.float64) if _is_numeric(action) else None
        if arr is None or arr.shape != (2 * N_DRONES,) or not np.all(np.isfinite(arr)):
            raise ValueError(
                f"action must be a finite [{2 * N_DRONES}] array in [-1, 1] (drone 0's "
                f"command, then drone 1's), got {action!r}."
            )
        cmd = arr.reshape(N_DRONES, 2)
        _, _, _, _, infos = self.arena.step(
            {a: cmd[self.arena._index[a]] for a in self.arena.agents})
        obs = self._joint_obs()
        reward = 0.0 if self.reward_fn is None else float(self.reward_fn(self._obs, arr, obs))
        terminated = not self.arena.active.any()
        truncated = not terminated and self.arena.timestep >= self.arena.max_steps
        self._obs = obs
        return obs.copy(), reward, terminated, truncated, self._joint_info(infos)

    def state(self) -> np.ndarray:
        """``[2, 4]`` float64 positions and velocities."""
        return self.arena.state()

    # ---- the solver's joint-env protocol (dicrl_torch.solvers.sac) ----------------
    def obs_from_states(self, states: Any) -> np.ndarray:
        """The joint observations ``[..., 20]`` of joint states ``[..., 2, 4]``
        (:func:`joint_obs_from_states`)."""
        return joint_obs_from_states(states)

    def set_rng(self, rng: np.random.Generator) -> None:
        """Draw the rest of this episode (its noise) and the unseeded resets after it
        from ``rng``: the arena's stream."""
        self.arena._rng = rng

    def vector_env(self, n_envs: int) -> DroneVectorEnv:
        """``n_envs`` episodes of this game (its arena's ``constrained``, ``max_steps``,
        ``dynamics`` and ``proximity_radius``; not its ``reward_fn``, as the solver
        rewards the transitions itself) stepped as one numpy computation.

        It exists for the solver's lean collection loop: stepping ``n_envs`` joint envs
        one by one costs a Python call chain per slot and step, while the batched
        :class:`~dicrl_torch.envs.drones.vector.DroneVectorEnv` gives the same
        transitions, bit for bit, with one :func:`joint_step` over all slots
        (:func:`dicrl_torch.envs.vector.vector_env_of` picks it up).
        """
        from dicrl_torch.envs.drones.vector import DroneVectorEnv

        arena = self.arena
        return DroneVectorEnv(n_envs, constrained=arena.constrained,
                              max_steps=arena.max_steps, dynamics=arena.dynamics,
                              proximity_radius=arena.proximity_radius)

    def set_constraint_overlay(self, cells: Any) -> None:
        """See :meth:`DroneArena.set_constraint_overlay`."""
        self.arena.set_constraint_overlay(cells)

    def render(self) -> np.ndarray | None:
        return self.arena.render()

    def close(self) -> None:
        self.arena.close()

