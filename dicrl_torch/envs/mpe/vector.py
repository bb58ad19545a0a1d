"""The constrained spread's joint env batched: :class:`SpreadVectorEnv`, ``n_envs``
episodes of ``spread_joint_env`` (``JointAgentEnv(ConstrainedSpread(...),
observation="state", use_state=True)``) stepped as one numpy computation.

The SAC solver collects its training transitions from a
:class:`~dicrl_torch.envs.vector.JointVectorEnv`. Stepped one by one
(:class:`~dicrl_torch.solvers.sac.env_list.EnvList`), each slot's step goes through
the joint wrapper, the PettingZoo checks, mpe2's per-entity Python loops and every
agent's observation and reward, which the solver never reads. Here the slots are arrays
(positions and velocities ``[n, N, 2]``) and one step replays, over all of them at
once, exactly the arithmetic of the reference:

1. mpe2's ``World.step`` (``apply_action_force``, ``apply_environment_force`` with
   ``get_collision_force``, ``integrate_state``): force ``= 5 * command``; a soft
   contact force between every pair of colliding agents (landmarks do not collide in
   ``simple_spread``), summed onto each agent in mpe2's pair order; position ``+= v dt``,
   damping, ``v += F / m dt``, mpe2's speed limit;
2. :meth:`ConstrainedSpread._step`'s additions: velocity noise, the env's speed limit,
   the walls, the disc and minimum-distance violations, freezing in the true game, and
   ``reached`` at the last step (:func:`~dicrl_torch.envs.mpe.layout.covering_agents`);
   the contact of two agents at one point is zero (where mpe2 divides by 0).

Every operation is the reference's, in its order (a sum of forces is a left fold in the
same order, norms are ``sqrt(x * x + y * y)`` as numpy's ``norm`` of a ``[2]`` vector
computes them), so the transitions are the reference's bit for bit
(``tests/test_vector_mpe.py`` measures a difference of 0). Only what draws from a slot's
own random stream loops over slots: the starts of a reset and, when ``noise_std > 0``,
the step's noise.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from dicrl_torch.checks import setting_int
from dicrl_torch.envs.joint import JointAgentEnv
from dicrl_torch.envs.mpe.env import ConstrainedSpread
from dicrl_torch.envs.mpe.layout import (
    MAX_SPEED,
    SpreadLayout,
    covering_agents,
    in_disc,
    sample_starts,
    sorted_assignment,
)
from dicrl_torch.envs.vector import (
    JointVectorEnv,
    VectorStep,
    generator_state_dict,
    restore_slot_generators,
)

__all__ = ["SpreadVectorEnv"]


class SpreadVectorEnv(JointVectorEnv):
    """``n_envs`` constrained-spread episodes in lock-step, each slot reset as it ends:
    the transitions of :class:`~dicrl_torch.solvers.sac.env_list.EnvList` over ``n_envs``
    ``JointAgentEnv(ConstrainedSpread(...), observation="state", use_state=True)``, as
    arrays.

    With ``n`` slots and ``N`` agents: actions ``[n, 2 N]`` (agent ``i``'s force command
    at ``2 i : 2 i + 2``, clipped to ``[-1, 1]``; a done agent's is ignored);
    observations ``[n, 4 N]`` float32, the flattened joint state; joint states ``[n, N,
    4]`` float64, ``x, y, vx, vy`` per agent. Usually built by
    :meth:`ConstrainedSpread.joint_vector_env` (through
    :meth:`JointAgentEnv.vector_env`).

    Args:
        n_envs: slots (``n``).
        layout, constrained, max_steps, noise_std, order_agents: the game's settings
            (:class:`~dicrl_torch.envs.mpe.ConstrainedSpread`; its ``local_ratio`` only
            weighs rewards, which a joint vector env does not give).
    """

    def __init__(self, n_envs: int, *, layout: SpreadLayout | None = None,
                 constrained: bool = True, max_steps: int = 50, noise_std: float = 0.0,
                 order_agents: bool = True) -> None:
        n = setting_int("n_envs", n_envs, example=4, why="slots stepped together")
        # The game checks the settings and holds mpe2's world, whose constants the
        # batched physics uses; its joint env gives the spaces, so they are the
        # reference's by construction.
        game = ConstrainedSpread(layout=layout, constrained=constrained, max_steps=max_steps,
                                 noise_std=noise_std, order_agents=order_agents)
        joint = JointAgentEnv(game, observation="state", use_state=True)
        self.game_name = str(game.metadata["name"])
        self.layout = game.layout
        self.constrained, self.max_steps = game.constrained, game.max_steps
        self.noise_std, self.order_agents = game.noise_std, game.order_agents
        self.n_envs, self.n_agents = n, game.n_agents
        self.state_shape = tuple(int(d) for d in joint.state_shape)
        self.observation_space, self.action_space = joint.observation_space, joint.action_space
        w = game._world
        agent = w.agents[0]
        self._sensitivity, self._dt, self._mass = game.sensitivity, game.dt, game.mass
        self._keep = 1 - w.damping  # mpe2: p_vel * (1 - damping)
        self._contact_force, self._margin = w.contact_force, w.contact_margin
        self._dist_min = agent.size + agent.size
        self._world_max_speed = float(agent.max_speed)
        # mpe2 gives contact forces only between colliding entities: the agents (while
        # flying). A landmark that collided would need its pairs here too.
        if any(lm.collide for lm in w.landmarks):  # pragma: no cover - mpe2's own choice
            raise NotImplementedError("colliding landmarks are not batched")
        self._landmarks = game.layout.landmark_array
        self._min_sq = game.layout.min_distance * game.layout.min_distance
        self._others = ~np.eye(self.n_agents, dtype=bool)
        joint.close()

        shape = (n, self.n_agents, 2)
        self._pos = np.zeros(shape)
        self._vel = np.zeros(shape)
        self._active = np.zeros((n, self.n_agents), dtype=bool)
        self._timestep = np.zeros(n, dtype=np.int64)
        self._rngs: list[np.random.Generator | None] = [None] * n
        self._started = False

    # ---- episode ------------------------------------------------------------------
    def reset(self, seeds: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
        """Every slot's first observation ``[n, 4 N]`` float32 and joint state ``[n, N,
        4]`` float64, slot ``k`` drawn from ``default_rng(seeds[k])`` (as
        ``ConstrainedSpread.reset(seed=seeds[k])``)."""
        seeds = list(seeds)
        if len(seeds) != self.n_envs:
            raise ValueError(f"reset needs one seed per slot ({self.n_envs}), got "
                             f"{len(seeds)}.")
        self._rngs = [np.random.default_rng(int(s)) for s in seeds]
        self._reset_slots(np.arange(self.n_envs))
        self._started = True
        states = self._states()
        return _flat(states), states

    def _reset_slots(self, slots: np.ndarray) -> None:
        """Start a new episode in ``slots``, each from its own stream (as
        ``ConstrainedSpread._reset``)."""
        for k in slots:
            pos = sample_starts(self.layout, self._rngs[k])
            assert pos is not None  # the layout checked that the region holds the agents
            if self.order_agents:  # agent k takes the k-th start of the matching's order
                pos = pos[np.argsort(sorted_assignment(self.layout, pos))]
            self._pos[k] = pos
        self._vel[slots] = 0.0
        self._active[slots] = True
        self._timestep[slots] = 0

    def step(self, actions: np.ndarray) -> VectorStep:
        """One step of every slot (``actions [n, 2 N]``); a slot whose episode ends is
        reset from its stream. See :class:`~dicrl_torch.envs.vector.VectorStep`."""
        if not self._started:
            raise RuntimeError("step() called before reset(); call reset(seeds) first.")
        cmd = self._commands(actions)  # [n, N, 2]
        before = self._active.copy()
        self._world_step(cmd, before)
        self._env_step(before)
        pos, active = self._pos, self._active
        layout = self.layout
        # Only agents flying before the step get an info this step; a frozen one stays
        # where it stopped and counts for nothing.
        disc = in_disc(pos, layout.disc_centre, layout.disc_radius) & before
        # pairwise_too_close(pos, min_distance, before) without its per-call eye
        diff = pos[:, :, None, :] - pos[:, None, :, :]  # [n, N, N, 2]
        close = ((diff * diff).sum(-1) < self._min_sq) & self._others \
            & before[:, :, None] & before[:, None, :]
        close = close.any(-1)
        violated = disc | close
        if self.constrained:  # violators freeze: stop, leave the episode, stop colliding
            self._vel[violated] = 0.0
            active &= ~violated
        self._timestep += 1
        last = self._timestep >= self.max_steps
        reached = np.zeros_like(violated)
        for k in np.flatnonzero(last):  # once per episode: the reference's own matching
            reached[k, active[k]] = covering_agents(pos[k][active[k]], self._landmarks)
        # JointAgentEnv: over when no agent flies or at the time limit; terminated when
        # every agent was terminated (froze), truncated when some flew to the end.
        terminated = ~active.any(-1)
        truncated = last & ~terminated
        states = self._states()
        final = _flat(states)
        obs = final.copy()
        done = np.flatnonzero(terminated | truncated)
        if done.size:
            self._reset_slots(done)
            obs[done] = _flat(self._states()[done])
        return VectorStep(obs=obs, final_obs=final, states=states, terminated=terminated,
                          truncated=truncated, reached=reached, violated=violated)

    def _commands(self, actions: Any) -> np.ndarray:
        """``[n, N, 2]`` float64 commands as the reference reads them: clipped to the
        joint action box ``[-1, 1]`` and cast to its float32 (``JointAgentEnv``), then
        to float64 (``ConstrainedSpread``, whose own clip to ``[-1, 1]`` changes nothing
        then)."""
        try:
            arr = np.asarray(actions, dtype=np.float64)
        except (TypeError, ValueError):
            arr = None
        shape = (self.n_envs, *self.action_space.shape)
        if arr is None or arr.shape != shape or not np.all(np.isfinite(arr)):
            raise ValueError(f"actions must be a finite {list(shape)} array (one joint "
                             f"action per slot: each agent's [2] force command in turn), "
                             f"got {np.shape(actions) if arr is None else list(arr.shape)}.")
        arr = np.minimum(np.maximum(arr, -1.0), 1.0).astype(np.float32).astype(np.float64)
        return arr.reshape(self.n_envs, self.n_agents, 2)

    def _world_step(self, cmd: np.ndarray, movable: np.ndarray) -> None:
        """mpe2's ``World.step`` over every slot (``cmd [n, N, 2]``, ``movable [n, N]``:
        the flying agents, which alone move and collide)."""
        pos, vel, n_agents = self._pos, self._vel, self.n_agents
        # apply_action_force: agent.action.u + 0.0 (no motor noise)
        force = self._sensitivity * cmd + 0.0
        # apply_environment_force: mpe2 visits pairs (a, b), a < b, adding +F to a and
        # -F to b, so agent i sums its pairs' forces in the order of the other agent j;
        # F(i, j) computed from p_i - p_j is exactly -F(j, i), as float negation is.
        delta = pos[:, :, None, :] - pos[:, None, :, :]  # [n, N, N, 2]
        dx, dy = delta[..., 0], delta[..., 1]
        dist = np.sqrt(dx * dx + dy * dy)
        same = (dx == 0) & (dy == 0)  # the env's NaN-safe contact: no force
        dist = np.where(same, 1.0, dist)
        k = self._margin
        penetration = np.logaddexp(0, -(dist - self._dist_min) / k) * k
        pair = self._contact_force * delta / dist[..., None] * penetration[..., None]
        collide = movable[:, :, None] & movable[:, None, :] & ~same  # no self-contact
        # A pair that gives no force (mpe2: None) adds 0.0 instead, which changes no sum
        # (at most the sign of a zero, which nothing after reads).
        pair = np.where(collide[..., None], pair, 0.0)
        for j in range(n_agents):
            force = pair[:, :, j] + force
        # integrate_state, for movable entities only
        new_pos = pos + vel * self._dt
        new_vel = vel * self._keep
        new_vel = new_vel + (force / self._mass) * self._dt
        speed = np.sqrt(new_vel[..., 0] * new_vel[..., 0] + new_vel[..., 1] * new_vel[..., 1])
        over = speed > self._world_max_speed
        if over.any():
            safe = np.where(over, speed, 1.0)[..., None]
            new_vel = np.where(over[..., None], new_vel / safe * self._world_max_speed,
                               new_vel)
        m = movable[..., None]
        self._pos = np.where(m, new_pos, pos)
        self._vel = np.where(m, new_vel, vel)

    def _env_step(self, flying: np.ndarray) -> None:
        """``ConstrainedSpread._step`` after mpe2's step: noise (drawn by every slot,
        for all its agents, as the reference draws it), the speed limit and the walls,
        for the agents ``flying [n, N]``."""
        vel = self._vel
        if self.noise_std:
            shape = (self.n_agents, 2)
            noise = np.stack([self.noise_std * rng.standard_normal(shape)
                              for rng in self._rngs])
            vel = vel + noise
        else:
            vel = vel + 0.0
        speed = np.sqrt(vel[..., 0] * vel[..., 0] + vel[..., 1] * vel[..., 1])
        over = speed > MAX_SPEED
        if over.any():
            scale = MAX_SPEED / np.where(over, speed, 1.0)
            vel = np.where(over[..., None], vel * scale[..., None], vel)
        h = self.layout.arena_half_width
        free = self._pos
        pos = np.clip(free, -h, h)
        vel = np.where(pos == free, vel, 0.0)  # an agent pushing into a wall stops there
        m = flying[..., None]
        self._pos = np.where(m, pos, free)
        self._vel = np.where(m, vel, self._vel)

    def _states(self) -> np.ndarray:
        """``[n, N, 4]`` float64 joint states (``ConstrainedSpread.state()`` per slot)."""
        return np.concatenate([self._pos, self._vel], axis=-1)

    def set_rng(self, slot: int, rng: np.random.Generator) -> None:
        """Draw the rest of slot ``slot``'s episode and its later resets from ``rng``."""
        if not isinstance(rng, np.random.Generator):
            raise ValueError(f"rng must be a numpy Generator, got {type(rng).__name__}.")
        self._rngs[int(slot)] = rng

    # ---- state --------------------------------------------------------------------
    def _settings(self) -> dict[str, Any]:
        lay = self.layout
        return {"constrained": self.constrained, "max_steps": self.max_steps,
                "noise_std": self.noise_std, "order_agents": self.order_agents,
                "layout": {"n_agents": lay.n_agents,
                           "landmarks": [list(p) for p in lay.landmarks],
                           "start_region": list(lay.start_region),
                           "disc_centre": list(lay.disc_centre),
                           "disc_radius": lay.disc_radius, "min_distance": lay.min_distance,
                           "arena_half_width": lay.arena_half_width}}

    def state_dict(self) -> dict[str, Any]:
        """Every slot in its current episode as tensors and plain python values:
        ``positions``/``velocities`` ``[n, N, 2]`` float64, ``active`` ``[n, N]`` bool,
        ``timestep`` ``[n]`` int64, each slot's random stream, and the game's settings
        (checked on loading)."""
        return {"game": self.game_name, "n_envs": self.n_envs, "started": self._started,
                "settings": self._settings(),
                **{key: torch.from_numpy(np.array(value)) for key, value in (
                    ("positions", self._pos), ("velocities", self._vel),
                    ("active", self._active), ("timestep", self._timestep))},
                "rngs": [generator_state_dict(g) for g in self._rngs]}

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        """Continue from a :meth:`state_dict` of a :class:`SpreadVectorEnv` with the same
        settings and ``n_envs``; a ValueError naming the first field that does not fit
        (nothing changed) otherwise."""

        fix = "load a state saved by a SpreadVectorEnv built with the same settings"
        if not isinstance(sd, dict):
            raise ValueError(f"spread vector env: the state must be a dict, got "
                             f"{type(sd).__name__}.")
        keys = ("game", "n_envs", "started", "settings", "positions", "velocities",
                "active", "timestep", "rngs")
        missing = [key for key in keys if key not in sd]
        if missing:
            raise ValueError(f"spread vector env: the state lacks {missing}; {fix}.")
        if sd["game"] != self.game_name:
            raise ValueError(f"spread vector env: the state is of game {sd['game']!r}, not "
                             f"{self.game_name!r}; {fix}.")
        if sd["n_envs"] != self.n_envs:
            raise ValueError(f"spread vector env: the state holds {sd['n_envs']} slots, this "
                             f"env {self.n_envs} (n_envs); {fix}.")
        if not isinstance(sd["settings"], dict):
            raise ValueError(f"spread vector env: the state's settings must be a dict; {fix}.")
        mine = self._settings()
        for key, value in mine.items():
            if sd["settings"].get(key) != value:
                raise ValueError(f"spread vector env: the state's {key} is "
                                 f"{sd['settings'].get(key)!r}, this env's {value!r}; {fix}.")
        n, n_agents = self.n_envs, self.n_agents
        expected = {"positions": ((n, n_agents, 2), torch.float64),
                    "velocities": ((n, n_agents, 2), torch.float64),
                    "active": ((n, n_agents), torch.bool), "timestep": ((n,), torch.int64)}
        arrays = {}
        for key, (shape, dtype) in expected.items():
            t = sd[key]
            if not isinstance(t, torch.Tensor) or tuple(t.shape) != shape or t.dtype != dtype:
                got = (f"{tuple(t.shape)} {t.dtype}" if isinstance(t, torch.Tensor)
                       else type(t).__name__)
                raise ValueError(f"spread vector env: the state's {key} must be a {shape} "
                                 f"{dtype} tensor, got {got}; {fix}.")
            arrays[key] = t.numpy().copy()
        if not np.all(np.isfinite(arrays["positions"])) \
                or not np.all(np.isfinite(arrays["velocities"])):
            raise ValueError(f"spread vector env: the state's positions and velocities must "
                             f"be finite; {fix}.")
        steps = arrays["timestep"]
        if np.any(steps < 0) or np.any(steps >= self.max_steps):
            raise ValueError(f"spread vector env: the state's timestep {steps.tolist()} must "
                             f"lie in [0, {self.max_steps}) (max_steps); {fix}.")
        if not isinstance(sd["rngs"], list) or len(sd["rngs"]) != n:
            raise ValueError(f"spread vector env: the state's rngs must be a list of {n} "
                             f"random streams; {fix}.")
        started = bool(sd["started"])
        rngs = restore_slot_generators(sd["rngs"], started, f"spread vector env ({fix})")
        self._pos, self._vel = arrays["positions"], arrays["velocities"]
        self._active, self._timestep = arrays["active"], arrays["timestep"]
        self._rngs, self._started = rngs, started


def _flat(states: np.ndarray) -> np.ndarray:
    """``[n, N, 4]`` joint states as ``[n, 4 N]`` float32 observations (the joint env's
    ``observation="state"``)."""
    return states.reshape(states.shape[0], -1).astype(np.float32)
