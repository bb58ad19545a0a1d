"""Many episodes of one joint game stepped together: what the SAC solver collects from.

A joint env (the protocol of :mod:`dicrl_torch.solvers.sac`) plays one episode at a
time, each step a Python call through its agents. The solver runs ``n_envs`` of them in
lock-step, so a game that can step all of them as one array computation offers a
:class:`JointVectorEnv` through its joint env's ``vector_env(n_envs)`` method (the
drone arena and the MPE spread do); any other joint env is stepped one by one by the
solver's :class:`~dicrl_torch.solvers.sac.env_list.EnvList`. Both give the same
transitions: ``tests/test_vector_drones.py`` and ``tests/test_vector_mpe.py`` check each
built-in game's batched env against its reference env, step by step.

Each slot ``k`` keeps its own random stream, drawn from in the reference env's order,
so slot ``k`` reset with seed ``s`` plays the episodes the reference env reset with
``seed=s`` plays. A slot whose episode ends is reset at once (without a seed: its
stream goes on); the step returns the finished episode's last observation and state
beside the new episode's first observation, as a vectorised env with auto-reset does.
"""

from __future__ import annotations

import abc
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
import torch

__all__ = ["JointVectorEnv", "VectorStep", "generator_state_dict", "restore_generator",
           "restore_slot_generators"]


@dataclass
class VectorStep:
    """One step of ``n`` slots (``N`` agents, joint states ``[N, d_s]``).

    Attributes:
        obs: ``[n, obs_dim]`` float32, what the next step acts on (a slot whose episode
            ended already holds its new episode's first observation).
        final_obs: ``[n, obs_dim]`` float32, the observation this step ended in (before
            any reset).
        states: ``[n, N, d_s]`` float64, the joint state this step ended in (the
            protocol's ``info["state"]``).
        terminated: ``[n]`` bool, the episode ended in a terminal state.
        truncated: ``[n]`` bool, the episode was cut (time limit), not terminal.
        reached: ``[n, N]`` bool, the step's ``info["reached"]``.
        violated: ``[n, N]`` bool, the step's ``info["violated"]``.
    """

    obs: np.ndarray
    final_obs: np.ndarray
    states: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    reached: np.ndarray
    violated: np.ndarray

    @property
    def done(self) -> np.ndarray:
        """``[n]`` bool: the slots whose episode ended (and were reset)."""
        return self.terminated | self.truncated


class JointVectorEnv(abc.ABC):
    """``n_envs`` episodes of a joint game in lock-step, each slot reset as it ends.

    Subclasses set :attr:`n_envs`, :attr:`n_agents`, :attr:`state_shape`,
    :attr:`observation_space` and :attr:`action_space` (the joint env's) and implement
    the methods below. Actions are the joint env's (in its action box).
    """

    n_envs: int
    n_agents: int
    state_shape: tuple[int, int]
    observation_space: gym.spaces.Box
    action_space: gym.spaces.Box

    @abc.abstractmethod
    def reset(self, seeds: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
        """Start an episode in every slot, slot ``k``'s stream seeded by ``seeds[k]`` (as
        the joint env's ``reset(seed=seeds[k])``): observations ``[n, obs_dim]`` float32
        and joint states ``[n, N, d_s]`` float64."""

    @abc.abstractmethod
    def step(self, actions: np.ndarray) -> VectorStep:
        """Step every slot with its joint action (``actions [n, d_a]``); a slot whose
        episode ends is reset (unseeded)."""

    @abc.abstractmethod
    def set_rng(self, slot: int, rng: np.random.Generator) -> None:
        """Draw the rest of slot ``slot``'s episode and its later resets from ``rng`` (the
        joint env's ``set_rng``)."""

    @abc.abstractmethod
    def state_dict(self) -> dict[str, Any]:
        """Every slot in its current episode (random streams included), as tensors and
        plain python values only (``torch.load(..., weights_only=True)`` reads it)."""

    @abc.abstractmethod
    def load_state_dict(self, sd: dict[str, Any]) -> None:
        """Continue from a :meth:`state_dict`; a ValueError naming the problem (nothing
        changed) unless it came from an env of the same game and ``n_envs``."""

    def close(self) -> None:  # noqa: B027 (an optional hook)
        """Release what the slots hold (nothing by default)."""


# ---- random streams as plain data (the vector envs' states and the solver's) --------
def _plain(value: Any) -> Any:
    """numpy arrays as tensors, numpy scalars as python ones, recursively."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, np.ndarray):
        return torch.from_numpy(np.array(value, copy=True))
    if isinstance(value, np.generic):
        return value.item()
    return value


def _native(value: Any) -> Any:
    """The inverse of :func:`_plain` (tensors back to numpy arrays)."""
    if isinstance(value, dict):
        return {k: _native(v) for k, v in value.items()}
    if isinstance(value, torch.Tensor):
        return value.numpy().copy()
    return value


def generator_state_dict(gen: np.random.Generator | None) -> dict[str, Any] | None:
    """The bit generator state of a numpy ``Generator`` (None for None) as plain data:
    for PCG64 (``default_rng``, gymnasium's seeding) python ints only."""
    return None if gen is None else _plain(gen.bit_generator.state)


def restore_generator(current: np.random.Generator | None,
                      sd: dict[str, Any] | None) -> np.random.Generator | None:
    """A generator in state ``sd``: ``current`` itself, set in place, when its bit
    generator is of the saved kind, else a new one (None for ``sd`` None)."""
    if sd is None:
        return None
    state = _native(sd)
    name = state["bit_generator"]
    if current is None or type(current.bit_generator).__name__ != name:
        current = np.random.Generator(getattr(np.random, name)())
    current.bit_generator.state = state
    return current


def restore_slot_generators(states: Sequence[Any], started: bool, where: str
                            ) -> list[np.random.Generator | None]:
    """A vector env's slot streams from their saved states, as new generators (so a
    failure leaves the env's own untouched); a ValueError naming the slot, ``where`` (the
    env and the fix), when one cannot be restored or a started env lacks one."""
    restored = []
    for k, state in enumerate(states):
        try:
            restored.append(restore_generator(None, state))
        except (AttributeError, KeyError, TypeError, ValueError) as e:
            raise ValueError(f"{where}: slot {k}'s random stream cannot be restored "
                             f"({e}).") from None
    if started and any(g is None for g in restored):
        raise ValueError(f"{where}: a started state lacks a slot's random stream.")
    return restored
