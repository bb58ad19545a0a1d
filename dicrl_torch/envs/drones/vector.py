"""The drone game's batched joint env (:mod:`dicrl_torch.envs.drones`): ``n_envs``
episodes of :class:`~dicrl_torch.envs.drones.env.JointDroneEnv` stepped as one numpy
computation, the :class:`~dicrl_torch.envs.vector.JointVectorEnv` the SAC solver collects
its transitions from.

:class:`DroneVectorEnv` plays, transition for transition, what an
:class:`~dicrl_torch.envs.vector.EnvList` of ``JointDroneEnv`` s with the same arena
settings plays: every slot keeps its own ``np.random.Generator`` and draws from it
exactly as the arena draws from its stream (the start jitter at a reset, then both
drones' noise at every step, flying or not), so only those draws loop over the slots;
the motion, the constraint checks and the observations are :func:`joint_step` and
:func:`joint_obs_from_states` over the whole ``[n_envs, N, ...]`` batch.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from dicrl_torch.checks import check_int, is_int
from dicrl_torch.envs.drones.dynamics import DroneDynamics, joint_step
from dicrl_torch.envs.drones.env import JointDroneEnv, joint_obs_from_states
from dicrl_torch.envs.drones.geometry import (
    N_DRONES,
    NOMINAL_STARTS,
    PROXIMITY_RADIUS,
    START_JITTER,
)
from dicrl_torch.envs.vector import (
    JointVectorEnv,
    VectorStep,
    generator_state_dict,
    restore_slot_generators,
)

__all__ = ["DroneVectorEnv"]

_GAME = "drone_arena"
"""The ``"game"`` tag of a :meth:`DroneVectorEnv.state_dict`, so that another game's
batched state is refused by name rather than by a shape that happens to differ."""
_STARTS = np.asarray(NOMINAL_STARTS, dtype=np.float64)  # [N, 2]


class DroneVectorEnv(JointVectorEnv):
    """``n_envs`` episodes of the drone game in lock-step, each slot reset as it ends.

    Equal, step for step and bit for bit, to ``EnvList(lambda: JointDroneEnv(**settings),
    n_envs)`` (``tests/test_vector_drones.py``). Build it through
    :meth:`JointDroneEnv.vector_env` to take a joint env's settings.

    Args:
        n_envs: slots (a positive int).
        constrained: True for the true game (violators freeze), False for the nominal.
        max_steps: episode limit in steps.
        dynamics: the drone dynamics (default :class:`DroneDynamics()`).
        proximity_radius: collision distance in metres.

    The arguments are checked as :class:`~dicrl_torch.envs.drones.env.DroneArena` checks
    them (a ValueError naming the bad one).
    """

    def __init__(self, n_envs: int, *, constrained: bool = True, max_steps: int = 300,
                 dynamics: DroneDynamics | None = None,
                 proximity_radius: float = PROXIMITY_RADIUS) -> None:
        self.n_envs = check_int("n_envs", n_envs)
        # The reference env checks the settings and defines the spaces; taking both from
        # one of it keeps the two from drifting apart.
        probe = JointDroneEnv(constrained=constrained, max_steps=max_steps,
                              dynamics=dynamics, proximity_radius=proximity_radius)
        arena = probe.arena
        self.constrained = arena.constrained
        self.max_steps = arena.max_steps
        self.dynamics = arena.dynamics
        self.proximity_radius = arena.proximity_radius
        self.n_agents = int(probe.n_agents)
        self.state_shape = tuple(int(d) for d in probe.state_shape)
        self.observation_space = probe.observation_space
        self.action_space = probe.action_space
        probe.close()
        # The arena clips each drone's float32 observation into these bounds
        # (PlanarCommandSpaces._bounded); the joint box is the two drones' bounds tiled.
        self._obs_low = self.observation_space.low
        self._obs_high = self.observation_space.high

        n = self.n_envs
        self._started = False
        self._states = np.zeros((n, N_DRONES, 4))  # [n, N, 4] float64
        self._active = np.zeros((n, N_DRONES), dtype=bool)  # [n, N] drones still flying
        self._timestep = np.zeros(n, dtype=np.int64)  # [n] steps into each episode
        self._rngs: list[np.random.Generator | None] = [None] * n

    # ---- episodes -----------------------------------------------------------------
    def reset(self, seeds: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
        """Start an episode in every slot, slot ``k``'s stream seeded by ``seeds[k]``.

        Args:
            seeds: ``n_envs`` ints (``JointDroneEnv.reset(seed=seeds[k])``).

        Returns:
            ``(obs [n, 20] float32, states [n, 2, 4] float64)``.
        """
        seeds = list(seeds)
        if len(seeds) != self.n_envs or not all(is_int(s) for s in seeds):
            raise ValueError(f"seeds must be {self.n_envs} ints (one per slot, n_envs), got "
                             f"{seeds!r}.")
        # As CheckedParallelEnv.reset: a seed gives a fresh default_rng stream.
        self._rngs = [np.random.default_rng(int(s)) for s in seeds]
        self._start(np.arange(self.n_envs))
        self._started = True
        return self._observe(self._states), self._states.copy()

    def _start(self, slots: np.ndarray) -> None:
        """Put ``slots`` (``[m]`` indices) at the start of a new episode, each drawing its
        start jitter from its own stream as ``DroneArena._reset`` does."""
        for k in slots:
            jitter = self._rngs[k].uniform(-START_JITTER, START_JITTER, size=(N_DRONES, 2))
            self._states[k, :, :2] = _STARTS + jitter
        self._states[slots, :, 2:] = 0.0
        self._active[slots] = True
        self._timestep[slots] = 0

    def step(self, actions: np.ndarray) -> VectorStep:
        """Step every slot with its joint action; a slot whose episode ends is reset from
        its own stream (unseeded).

        Args:
            actions: ``[n, 4]`` per slot drone 0's command then drone 1's, clipped to
                ``[-1, 1]``; a done drone's command is ignored.

        Returns:
            The :class:`~dicrl_torch.envs.vector.VectorStep` (``obs``/``final_obs``
            ``[n, 20]`` float32, ``states`` ``[n, 2, 4]`` float64, ``terminated``/
            ``truncated`` ``[n]`` bool, ``reached``/``violated`` ``[n, 2]`` bool).
        """
        if not self._started:
            raise RuntimeError("step() called before reset(); call reset(seeds) first.")
        command = self._check_actions(actions)
        n = self.n_envs
        noise = np.empty((n, N_DRONES, 2))
        for k, rng in enumerate(self._rngs):
            # Every step draws both drones' noise, flying or not (DroneArena._step).
            noise[k] = self.dynamics.sample_noise(rng, (N_DRONES, 2))
        res = joint_step(self._states, command, self._active, noise, dynamics=self.dynamics,
                         proximity_radius=self.proximity_radius,
                         constrained=self.constrained)
        # The reference reports a drone's flags only for the agents still live before the
        # step (JointDroneEnv._joint_info gives False for the others); joint_step already
        # gives False for inactive drones, so the mask only states the contract.
        reached = res.reached & self._active
        violated = res.violated & self._active
        self._states, self._active = res.state, res.active
        self._timestep += 1
        terminated = ~self._active.any(1)
        truncated = ~terminated & (self._timestep >= self.max_steps)
        states = self._states.copy()
        final_obs = self._observe(states)
        obs = final_obs.copy()
        done = np.flatnonzero(terminated | truncated)
        if done.size:
            self._start(done)
            obs[done] = self._observe(self._states[done])
        return VectorStep(obs=obs, final_obs=final_obs, states=states, terminated=terminated,
                          truncated=truncated, reached=reached, violated=violated)

    def _check_actions(self, actions: Any) -> np.ndarray:
        """``actions`` as ``[n, N, 2]`` float64 commands clipped to ``[-1, 1]`` (as
        ``DroneArena._check_command``; the disc's norm bound applies after the clip)."""
        try:
            arr = np.asarray(actions, dtype=np.float64)
        except (TypeError, ValueError):
            arr = None
        want = (self.n_envs, 2 * N_DRONES)
        if arr is None or arr.shape != want or not np.all(np.isfinite(arr)):
            shape = None if arr is None else list(arr.shape)
            raise ValueError(f"actions must be a finite {list(want)} array in [-1, 1] (per slot "
                             f"drone 0's command, then drone 1's), got shape {shape}.")
        return np.clip(arr, -1.0, 1.0).reshape(self.n_envs, N_DRONES, 2)

    def _observe(self, states: np.ndarray) -> np.ndarray:
        """``[m, 20]`` float32 joint observations of ``states [m, 2, 4]``, clipped into the
        observation box as ``DroneArena.observe`` clips each drone's."""
        return np.clip(joint_obs_from_states(states), self._obs_low, self._obs_high)

    def set_rng(self, slot: int, rng: np.random.Generator) -> None:
        """Draw the rest of slot ``slot``'s episode and its later resets from ``rng``
        (``JointDroneEnv.set_rng``: the generator itself, not a copy)."""
        if not is_int(slot) or not 0 <= slot < self.n_envs:
            raise ValueError(f"slot must be an int in [0, {self.n_envs}), got {slot!r}.")
        if not isinstance(rng, np.random.Generator):
            raise ValueError(f"rng must be a numpy Generator, got {type(rng).__name__}.")
        self._rngs[int(slot)] = rng

    # ---- state --------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """Every slot in its current episode as tensors and plain python values:
        ``states [n, 2, 4]`` float64, ``active [n, 2]`` bool, ``timestep [n]`` int64 and
        each slot's generator state (None before the first reset)."""
        return {
            "game": _GAME,
            "n_envs": self.n_envs,
            "started": self._started,
            "states": torch.from_numpy(self._states.copy()),
            "active": torch.from_numpy(self._active.copy()),
            "timestep": torch.from_numpy(self._timestep.copy()),
            "rngs": [generator_state_dict(r) for r in self._rngs],
        }

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        """Continue from a :meth:`state_dict`; a ValueError naming the first field that
        does not fit (another game, another ``n_envs``, a bad array or stream), with
        nothing changed."""
        if not isinstance(sd, dict) or sd.get("game") != _GAME:
            got = sd.get("game") if isinstance(sd, dict) else type(sd).__name__
            raise ValueError(f"drone vector env: the state is not a drone arena's batched "
                             f"state (game {got!r}); load a DroneVectorEnv.state_dict().")
        missing = [k for k in ("n_envs", "started", "states", "active", "timestep", "rngs")
                   if k not in sd]
        if missing:
            raise ValueError(f"drone vector env: the state lacks {missing}; load a "
                             f"DroneVectorEnv.state_dict().")
        n = self.n_envs
        if not is_int(sd["n_envs"]) or int(sd["n_envs"]) != n:
            raise ValueError(f"drone vector env: the state holds {sd['n_envs']!r} slots, this "
                             f"env {n} (n_envs); load it into an env with as many slots.")
        states = _checked_array("states", sd["states"], (n, N_DRONES, 4), np.float64)
        active = _checked_array("active", sd["active"], (n, N_DRONES), np.bool_)
        timestep = _checked_array("timestep", sd["timestep"], (n,), np.int64)
        if not np.all(np.isfinite(states)) or (timestep < 0).any():
            raise ValueError("drone vector env: the state holds non-finite states or "
                             "negative timesteps; load a DroneVectorEnv.state_dict().")
        rngs = sd["rngs"]
        if not isinstance(rngs, list | tuple) or len(rngs) != n:
            raise ValueError(f"drone vector env: the state's 'rngs' must be a list of {n} "
                             f"generator states, got {type(rngs).__name__}.")
        # Fresh generators, so that a bad stream in a later slot leaves this env's
        # streams (possibly shared with a caller through set_rng) untouched.
        started = bool(sd["started"])
        restored = restore_slot_generators(
            rngs, started, "drone vector env (load a DroneVectorEnv.state_dict())")
        self._states, self._active, self._timestep = states, active, timestep
        self._rngs, self._started = restored, started


def _checked_array(key: str, got: Any, shape: tuple[int, ...], dtype: Any) -> np.ndarray:
    """``got`` as a numpy copy; a ValueError naming ``key`` unless it is a ``shape``
    tensor of ``dtype``."""
    want = torch.from_numpy(np.empty(0, dtype=dtype)).dtype
    if not isinstance(got, torch.Tensor) or tuple(got.shape) != shape or got.dtype != want:
        what = (f"shape {list(got.shape)} {got.dtype}" if isinstance(got, torch.Tensor)
                else f"a {type(got).__name__}")
        raise ValueError(f"drone vector env: the state's {key!r} is {what}, this env needs "
                         f"shape {list(shape)} {want}; load it into an env with the same "
                         f"n_envs.")
    return got.numpy().copy()
