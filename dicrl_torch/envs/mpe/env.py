"""The constrained spread as a PettingZoo ``ParallelEnv``: :class:`ConstrainedSpread`,
the game of :mod:`dicrl_torch.envs.mpe` (its geometry and checks are
:mod:`dicrl_torch.envs.mpe.layout`, its picture :mod:`dicrl_torch.envs.mpe.render`).

**How it is built on mpe2.** mpe2's ``simple_spread`` is an AEC env (a turn-based
wrapper around a physics ``World``) whose ``reset`` draws random agent and landmark
positions; its parallel version is a conversion wrapper. Freezing an agent, fixing the
landmarks and drawing starts from a region do not fit through that public API, so this
env composes mpe2's pieces below it: the ``simple_spread`` :class:`Scenario` builds the
``World`` (agents of size 0.15, silent, landmarks), gives each agent's observation and
each agent's reward, and mpe2's ``World.step`` integrates the physics (force =
``5 * command``, mass 1, damping 0.25, dt 0.1, soft contact forces between agents). This
env adds only what the task needs: fixed landmarks and the start region, the
constraints and freezing, walls (a square arena, so that observations are bounded; an
agent pushing into a wall stops against it, as in the drone arena) and a speed limit
(mpe2's own ``max_speed`` attribute) for the same reason. mpe2's continuous action
``[no_op, left, right, down, up]`` in ``[0, 1]^5`` moves an agent by ``(right - left,
up - down)`` only; this env takes that effective command ``[2]`` in ``[-1, 1]^2``
directly (the symmetric box SAC expects). A frozen agent is marked ``movable = False``
and ``collide = False`` in the world. mpe2's contact force is undefined (NaN) for two
agents at the same point, which the walls make possible (two agents pushed into one
corner); there this env makes it zero.

Observation of agent ``i`` (float32, ``6 N`` values, mpe2's ``simple_spread``
observation): own velocity ``[2]``, own position ``[2]``, the landmarks' positions
relative to it ``[2 N]``, the other agents' relative positions ``[2 (N - 1)]`` and their
communication ``[2 (N - 1)]`` (always 0: the agents are silent). Bounded by the walls
and the speed limit. Reward: mpe2's, ``(1 - local_ratio) * global + local_ratio *
local`` with global = minus the sum over landmarks of the distance to the nearest agent
and local = −1 per agent in contact (the learner brings its own reward anyway).
"""

from __future__ import annotations

import types
from typing import Any

import numpy as np
from gymnasium import spaces
from mpe2.simple_spread.simple_spread import Scenario as SpreadScenario

from dicrl_torch.checks import setting_int
from dicrl_torch.envs.mpe.layout import (
    MAX_SPEED,
    SpreadLayout,
    check_number,
    covering_agents,
    in_disc,
    landmarks_covered,
    pairwise_too_close,
    sample_starts,
    sorted_assignment,
)
from dicrl_torch.envs.mpe.render import render_spread
from dicrl_torch.envs.parallel import CheckedParallelEnv
from dicrl_torch.envs.planar import PlanarCommandSpaces


def _collision_force(world: Any, entity_a: Any, entity_b: Any) -> list[Any]:
    """mpe2's contact force (``World.get_collision_force``), which divides by the
    distance: two agents pushed into the same corner of the walls sit at the same point,
    where it has no direction and mpe2 would give NaN; there it is zero."""
    if entity_a is not entity_b and entity_a.collide and entity_b.collide \
            and np.array_equal(entity_a.state.p_pos, entity_b.state.p_pos):
        return [None, None]
    return type(world).get_collision_force(world, entity_a, entity_b)


def _agent_names(n: int) -> list[str]:
    return [f"agent_{i}" for i in range(n)]


class ConstrainedSpread(PlanarCommandSpaces, CheckedParallelEnv):
    """MPE ``simple_spread`` with fixed landmarks, a start region, a forbidden disc and
    a minimum inter-agent distance; the true game or its nominal game
    (:mod:`dicrl_torch.envs.mpe`).

    Agents ``agent_0 … agent_{N-1}``. Observation of each: ``[6 N]`` float32 (mpe2's).
    Action of each: ``[2]`` float32 force command in ``[-1, 1]^2`` (clipped). Reward:
    mpe2's ``simple_spread`` reward. The state (:meth:`state`) is ``[N, 4]`` float64:
    ``x, y, vx, vy`` per agent. ``infos[agent]`` has ``violated`` (this step),
    ``in_disc``, ``too_close``, ``position`` (``[2]`` float64) and ``reached``: at the
    last step (``max_steps``), whether the agent, still flying, then covers a landmark in
    a maximum matching (:func:`covering_agents`); False before. So every agent of an
    episode reached its goal, with no violation, exactly when :meth:`task_success`. In
    the true game a violator is terminated; every agent still flying is truncated after
    ``max_steps`` (episodes always last ``max_steps`` steps unless every agent froze).
    The random stream (starts, noise) depends only on the seed.

    Args:
        layout: the geometry (default :class:`SpreadLayout()`: 2 agents).
        constrained: True for the true game (violators freeze), False for the nominal.
        max_steps: episode length in steps of 0.1 (default 50). The via-point
            controller covers the landmarks for good within 23 steps with 2 agents and
            26 with 3 (measured on 100 seeded episodes each).
        local_ratio: mpe2's mix of the local and global reward (0.5).
        noise_std: standard deviation of Gaussian noise added to each flying agent's
            velocity per step, from the env's seeded generator (default 0: mpe2's
            deterministic physics).
        order_agents: number the drawn starts so that agent ``k``'s landmark in the
            order-preserving matching (:func:`sorted_assignment`) is landmark ``k``. The
            agents are interchangeable, so this is a labelling, not a change of the
            game; it spares a joint policy learning each assignment once per start
            order (without it SAC policies learned one order and failed the mirror one:
            docs/mpe.md). Starts given in ``options`` keep the caller's order.
        render_mode: None or ``"rgb_array"``.
    """

    metadata = {"render_modes": ["rgb_array"], "name": "constrained_spread_v0",
                "is_parallelizable": True, "render_fps": 10}

    def __init__(
        self,
        *,
        layout: SpreadLayout | None = None,
        constrained: bool = True,
        max_steps: int = 50,
        local_ratio: float = 0.5,
        noise_std: float = 0.0,
        order_agents: bool = True,
        render_mode: str | None = None,
    ) -> None:
        if layout is None:
            layout = SpreadLayout()
        if not isinstance(layout, SpreadLayout):
            raise ValueError(f"layout must be a SpreadLayout, got {type(layout).__name__}; "
                             f"build one with SpreadLayout(n_agents=..., ...).")
        if not isinstance(constrained, bool | np.bool_):
            raise ValueError(f"constrained must be a bool (True: true game, False: nominal "
                             f"game), got {constrained!r}.")
        setting_int("max_steps", max_steps, example=50, why="episode limit in steps")
        local_ratio = check_number("local_ratio", local_ratio)
        if local_ratio > 1:
            raise ValueError(f"local_ratio must lie in [0, 1], got {local_ratio!r}.")
        self._check_render_mode(render_mode)
        self.layout = layout
        self.constrained = bool(constrained)
        self.max_steps = int(max_steps)
        self.local_ratio = local_ratio
        self.noise_std = check_number("noise_std", noise_std)
        if not isinstance(order_agents, bool | np.bool_):
            raise ValueError(f"order_agents must be a bool, got {order_agents!r}.")
        self.order_agents = bool(order_agents)
        self.render_mode = render_mode
        n = self.n_agents = layout.n_agents
        self.possible_agents = _agent_names(n)
        self._index = {a: i for i, a in enumerate(self.possible_agents)}

        self._scenario = SpreadScenario()
        self._world = self._scenario.make_world(n)
        self._world.get_collision_force = types.MethodType(_collision_force, self._world)
        for agent in self._world.agents:
            agent.max_speed = MAX_SPEED
        w = self._world
        # mpe2's continuous action processing: force = sensitivity * command.
        self.sensitivity = float(w.agents[0].accel or 5.0)
        self.dt, self.damping, self.mass = float(w.dt), float(w.damping), \
            float(w.agents[0].mass)

        h = layout.arena_half_width
        obs_bound = np.concatenate([
            np.full(2, MAX_SPEED), np.full(2, h), np.full(2 * n, 2 * h),
            np.full(2 * (n - 1), 2 * h), np.ones(w.dim_c * (n - 1)),
        ]).astype(np.float32)
        self._obs_high, self._obs_low = obs_bound, -obs_bound
        bound = np.tile(np.array([h, h, MAX_SPEED, MAX_SPEED]), (n, 1))
        self.state_space = spaces.Box(low=-bound, high=bound, dtype=np.float64)

        self.agents: list[str] = []
        self.timestep = 0
        self._started = False
        self._active = np.zeros(n, dtype=bool)
        self.violated = np.zeros(n, dtype=bool)  # ever violated, this episode
        self._history: list[np.ndarray] = []
        self._rng: np.random.Generator | None = None

    # ---- episode ------------------------------------------------------------------
    @property
    def started(self) -> bool:
        return self._started

    def _reset(self, options: dict[str, Any] | None
               ) -> tuple[dict[str, np.ndarray], dict[str, dict[str, Any]]]:
        """``reset(options={"positions": [[x, y], ...]})`` sets the starts (anywhere in the
        arena off the constraints) instead of drawing them (other keys are ignored)."""
        pos = sample_starts(self.layout, self._rng)
        assert pos is not None  # the layout checked that the region holds the agents
        if self.order_agents:  # agent k takes the k-th start of the matching's order
            pos = pos[np.argsort(sorted_assignment(self.layout, pos))]
        if options and options.get("positions") is not None:
            pos = self.layout.check_starts(options["positions"])
        w = self._world
        for agent, p in zip(w.agents, pos, strict=True):
            agent.state.p_pos = p.copy()
            agent.state.p_vel = np.zeros(w.dim_p)
            agent.state.c = np.zeros(w.dim_c)
            agent.action.u = np.zeros(w.dim_p)
            agent.action.c = np.zeros(w.dim_c)
            agent.movable = agent.collide = True
        for landmark, p in zip(w.landmarks, self.layout.landmark_array, strict=True):
            landmark.state.p_pos = p.copy()
            landmark.state.p_vel = np.zeros(w.dim_p)
        self._active = np.ones(self.n_agents, dtype=bool)
        self.violated = np.zeros(self.n_agents, dtype=bool)
        self.timestep = 0
        self._started = True
        self._history = [pos.copy()]
        self.agents = list(self.possible_agents)
        obs = {a: self.observe(a) for a in self.agents}
        infos = {a: self._info(i, False, False) for a, i in self._index.items()}
        return obs, infos

    def _step(self, given: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        """The step of :meth:`CheckedParallelEnv.step`; ``given`` holds a ``[2]`` command
        for every live agent."""
        w, n = self._world, self.n_agents
        command = np.zeros((n, 2))
        for agent, a in given.items():
            command[self._index[agent]] = self._check_command(agent, a)
        for i, agent in enumerate(w.agents):
            agent.action.u = self.sensitivity * command[i] if self._active[i] \
                else np.zeros(w.dim_p)
            agent.action.c = np.zeros(w.dim_c)
        w.step()  # mpe2's physics; frozen agents are not movable
        noise = self.noise_std * self._rng.standard_normal((n, 2)) if self.noise_std else None
        h = self.layout.arena_half_width
        for i, agent in enumerate(w.agents):
            if not self._active[i]:
                continue
            vel = agent.state.p_vel + (0.0 if noise is None else noise[i])
            speed = np.linalg.norm(vel)
            if speed > MAX_SPEED:
                vel = vel * (MAX_SPEED / speed)
            free = agent.state.p_pos
            pos = np.clip(free, -h, h)
            agent.state.p_pos = pos
            agent.state.p_vel = np.where(pos == free, vel, 0.0)
        positions = self.positions
        layout = self.layout
        disc = in_disc(positions, layout.disc_centre, layout.disc_radius) & self._active
        close = pairwise_too_close(positions, layout.min_distance, self._active)
        violated = disc | close
        self.violated |= violated
        if self.constrained:
            for i in np.flatnonzero(violated):
                agent = w.agents[i]
                agent.state.p_vel = np.zeros(w.dim_p)
                agent.movable = agent.collide = False
            self._active = self._active & ~violated
        self.timestep += 1
        self._history.append(positions.copy())

        global_reward = float(self._scenario.global_reward(w))
        # Success is judged at the end: only the last step reports the agents that then
        # cover a landmark (``reached``), so a solver's "reached in the episode" is
        # "covering at the end".
        last = self.timestep >= self.max_steps
        covering = np.zeros(self.n_agents, dtype=bool)
        if last:  # frozen agents cover nothing (a violation already failed the task)
            covering[self._active] = covering_agents(positions[self._active],
                                                     layout.landmark_array)
        obs, rewards, terms, truncs, infos = {}, {}, {}, {}, {}
        for a in given:
            i = self._index[a]
            obs[a] = self.observe(a)
            local = float(self._scenario.reward(w.agents[i], w))
            rewards[a] = (1 - self.local_ratio) * global_reward + self.local_ratio * local
            terms[a] = not bool(self._active[i])
            truncs[a] = not terms[a] and last
            infos[a] = self._info(i, bool(disc[i]), bool(close[i]),
                                  reached=bool(covering[i]))
        self.agents = [a for a in given if not (terms[a] or truncs[a])]
        return obs, rewards, terms, truncs, infos

    def observe(self, agent: str) -> np.ndarray:
        """``[6 N]`` float32 observation of ``agent`` (also for agents that are done)."""
        i = self._agent_index(agent)
        self._require_started("observe")
        o = self._scenario.observation(self._world.agents[i], self._world)
        return self._bounded(o)  # the walls and the speed limit keep o inside the bounds

    def state(self) -> np.ndarray:
        """``[N, 4]`` float64 ``x, y, vx, vy`` per agent (frozen agents where they stopped)."""
        self._require_started("state")
        return np.array([np.concatenate([a.state.p_pos, a.state.p_vel])
                         for a in self._world.agents])

    @property
    def positions(self) -> np.ndarray:
        """``[N, 2]`` float64 positions."""
        return self.state()[:, :2]

    @property
    def active(self) -> np.ndarray:
        """``[N]`` bool: agents not frozen (in the nominal game: all)."""
        return self._active.copy()

    def trajectory(self) -> np.ndarray:
        """``[t+1, N, 2]`` float64 positions since the last reset."""
        return np.stack(self._history) if self._history \
            else np.zeros((0, self.n_agents, 2))

    def landmarks_covered(self) -> bool:
        """Whether every landmark is now within :data:`SUCCESS_RADIUS` of a distinct agent."""
        return landmarks_covered(self.positions, self.layout.landmark_array)

    def task_success(self) -> bool:
        """The task-success test, meant for the end of an episode: every landmark within
        :data:`SUCCESS_RADIUS` of a distinct agent and no violation in the episode."""
        return self.landmarks_covered() and not self.violated.any()

    def joint_vector_env(self, n_envs: int) -> Any:
        """``n_envs`` episodes of this game's joint env (``JointAgentEnv(self,
        observation="state", use_state=True)``, as ``spread_joint_env`` builds it)
        stepped as one array computation: a
        :class:`~dicrl_torch.envs.mpe.vector.SpreadVectorEnv` with this game's settings
        (``local_ratio`` aside: it only weighs rewards, which a vector env does not
        give). The SAC solver's lean collection loop steps it instead of ``n_envs``
        copies of the joint env, one Python call chain per agent each, and gets the same
        transitions (observations ``[n, 4 N]``, states ``[n, N, 4]``)."""
        from dicrl_torch.envs.mpe.vector import SpreadVectorEnv  # it imports this module

        return SpreadVectorEnv(n_envs, layout=self.layout, constrained=self.constrained,
                               max_steps=self.max_steps, noise_std=self.noise_std,
                               order_agents=self.order_agents)

    # ---- rendering ----------------------------------------------------------------
    def _render(self) -> np.ndarray:
        title = f"{self.metadata['name']}  t={self.timestep}/{self.max_steps}" + (
            "" if self.constrained else "  (nominal)")
        started = self._started
        return render_spread(
            self.layout, trajectories=[self.trajectory()] if started else None,
            positions=self.positions if started else None,
            frozen=~self._active if started and self.constrained else None, title=title)

    # ---- helpers ------------------------------------------------------------------
    def _info(self, i: int, disc: bool, close: bool, reached: bool = False) -> dict[str, Any]:
        return {"violated": disc or close, "in_disc": disc, "too_close": close,
                "reached": reached, "position": self._world.agents[i].state.p_pos.copy()}

    def _check_command(self, agent: str, a: Any) -> np.ndarray:
        """``a`` as a ``[2]`` float64 command, clipped to ``[-1, 1]``."""
        try:
            arr = np.asarray(a, dtype=np.float64)
        except (TypeError, ValueError):
            arr = None
        if arr is None or arr.shape != (2,) or not np.all(np.isfinite(arr)):
            raise ValueError(f"Action of {agent} must be a finite [2] force command in "
                             f"[-1, 1] (right - left, up - down), got {a!r}.")
        return np.clip(arr, -1.0, 1.0)
