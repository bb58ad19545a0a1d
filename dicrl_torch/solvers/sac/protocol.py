"""The joint env the SAC solver drives and the demonstrations it reads: the checks of the
protocol written down in :mod:`dicrl_torch.solvers.sac` ("The joint-env protocol").

Every refusal happens when the solver is built or the demonstrations are handed over,
with the field and the fix named, never deep inside SB3.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from dicrl_torch.demos.continuous import ContinuousDemonstrations
from dicrl_torch.solvers.sac.checks import _is_int
from dicrl_torch.solvers.sac.randomness import capture_global_rng, restore_global_rng

__all__ = ["JointEnvSpec", "as_continuous", "check_joint_env", "make_joint_env",
           "protocol_attr", "step_fields"]

_PROTOCOL = "the joint-env protocol of dicrl_torch.solvers.sac"


def protocol_attr(env: gym.Env, name: str) -> Any:
    """``env``'s attribute ``name``, looked up through its gymnasium wrappers (a
    ``Monitor``, a ``TimeLimit``...), or None when no layer has it."""
    try:
        return env.get_wrapper_attr(name)
    except AttributeError:
        return None


def make_joint_env(env_factory: Callable[..., gym.Env], constrained: bool) -> gym.Env:
    """``env_factory(constrained=constrained)``, refused unless it is a gymnasium env."""
    try:
        env = env_factory(constrained=constrained)
    except TypeError as e:
        raise ValueError(
            f"env_factory(constrained={constrained}) failed ({e}); the factory must take "
            f"the keyword constrained (False: the nominal game the solver trains in, True: "
            f"the true game of evaluate(true_game=True)), e.g. functools.partial("
            f"JointAgentEnv-building function, ...) or a class accepting constrained."
        ) from e
    if not isinstance(env, gym.Env):
        hint = ("wrap a PettingZoo ParallelEnv with dicrl_torch.envs.joint.JointAgentEnv"
                if hasattr(env, "possible_agents") else "return a gymnasium.Env")
        raise ValueError(f"env_factory returned a {type(env).__name__}, not a gymnasium "
                         f"env moving all agents at once; {hint}.")
    return env


@dataclass(frozen=True)
class JointEnvSpec:
    """What the solver knows of its joint env (read once, from a probe env).

    Attributes:
        name: the env's class, for messages and the state's settings.
        n_agents: ``N``.
        state_shape: ``(N, d_s)`` of ``info["state"]``.
        observation_space: the joint observation ``Box``.
        action_space: the joint action ``Box`` (the agents' actions concatenated).
    """

    name: str
    n_agents: int
    state_shape: tuple[int, int]
    observation_space: spaces.Box
    action_space: spaces.Box

    @property
    def action_dim(self) -> int:
        return int(np.prod(self.action_space.shape))

    @property
    def unit_actions(self) -> bool:
        """Whether the action box is ``[-1, 1]^d``, SAC's squashed range (then actions
        need no rescaling, and none is done: not even a rounding step)."""
        return bool(np.all(self.action_space.low == -1) and np.all(self.action_space.high == 1))

    def to_policy(self, actions: np.ndarray) -> np.ndarray:
        """Env actions ``[..., d]`` mapped onto SAC's ``[-1, 1]^d`` (as SB3 stores them)."""
        if self.unit_actions:
            return actions
        low, high = self.action_space.low, self.action_space.high
        return 2.0 * (actions - low) / (high - low) - 1.0

    def to_env(self, actions: np.ndarray) -> np.ndarray:
        """SAC's ``[-1, 1]^d`` actions mapped onto the env's box (the inverse)."""
        if self.unit_actions:
            return actions
        low, high = self.action_space.low, self.action_space.high
        return low + 0.5 * (actions + 1.0) * (high - low)

    def describe(self) -> str:
        """The env as a state's settings compare it: class, agents, state and spaces."""
        return (f"{self.name} N={self.n_agents} state={list(self.state_shape)} "
                f"obs={list(self.observation_space.shape)} "
                f"action={list(self.action_space.shape)}")


def check_joint_env(env: gym.Env) -> JointEnvSpec:
    """The :class:`JointEnvSpec` of ``env``, or a ValueError naming what breaks the
    protocol and the fix. ``env`` is reset once (``seed=0``) to check the state of its
    ``info``; the caller's global random streams are left as they were."""
    name = type(env.unwrapped).__name__
    act = env.action_space
    if not isinstance(act, spaces.Box):
        raise ValueError(
            f"{name} has the action space {act!r}; the SAC solver needs continuous "
            f"actions: a Box joint action (every agent's Box action concatenated). Make "
            f"the game with continuous actions (e.g. mpe2's parallel_env("
            f"continuous_actions=True)) and wrap it with JointAgentEnv, which refuses a "
            f"discrete agent by name.")
    if len(act.shape) != 1 or not np.all(np.isfinite(act.low)) \
            or not np.all(np.isfinite(act.high)):
        raise ValueError(f"{name}'s action space {act!r} must be a flat Box with finite "
                         f"bounds (SAC squashes its actions into them); clip and flatten "
                         f"the actions in a wrapper.")
    if not isinstance(env.observation_space, spaces.Box):
        raise ValueError(f"{name}'s observation space {env.observation_space!r} must be a "
                         f"Box; use JointAgentEnv(observation='state') or flatten it.")
    n = protocol_attr(env, "n_agents")
    shape = protocol_attr(env, "state_shape")
    if not _is_int(n) or n < 1 or shape is None or len(tuple(shape)) != 2 \
            or tuple(shape)[0] != n or not all(_is_int(d) and d >= 1 for d in shape):
        raise ValueError(
            f"{name} must say how many agents it moves and the shape of its joint state "
            f"(attributes n_agents = N and state_shape = (N, d_s)), got n_agents={n!r}, "
            f"state_shape={shape!r}; see {_PROTOCOL}. JointAgentEnv has both (state_shape "
            f"is None when the agents' observations differ in width and there is no "
            f"env.state(): give the game a state_space).")
    shape = (int(shape[0]), int(shape[1]))
    caller = capture_global_rng(False)  # an unknown env may draw from the global streams
    try:
        _, info = env.reset(seed=0)
    finally:
        restore_global_rng(caller, False)
    state = np.asarray(info.get("state") if isinstance(info, dict) else None)
    if state.shape != shape or not np.issubdtype(state.dtype, np.number):
        raise ValueError(
            f"{name}.reset() must give info['state'], the joint state [N, d_s] = "
            f"{list(shape)} the feature bases read (also in every step's info), got "
            f"{None if state.ndim == 0 else list(state.shape)}; see {_PROTOCOL}.")
    return JointEnvSpec(name=name, n_agents=int(n), state_shape=shape,
                        observation_space=env.observation_space, action_space=act)


def step_fields(info: dict[str, Any],
                keys: tuple[str, ...] = ("state", "reached", "violated")) -> tuple[Any, ...]:
    """``info[key]`` for each of ``keys`` (by default the step's ``state``,
    ``reached`` and ``violated``), or a ValueError naming the missing key."""
    try:
        return tuple(info[key] for key in keys)
    except KeyError as e:
        raise ValueError(f"The env's step info has no {e.args[0]!r}: every step must give "
                         f"'state' [N, d_s] and the per-agent [N] bools 'reached' and "
                         f"'violated' (False where the game has no such notion); see "
                         f"{_PROTOCOL}.") from None


def as_continuous(demos: Any, spec: JointEnvSpec | None = None) -> ContinuousDemonstrations:
    """``demos`` as :class:`ContinuousDemonstrations` (anything with ``to_continuous()``
    is converted), checked against the env's shapes when ``spec`` is given.

    Raises:
        ValueError: not demonstrations, or their ``states`` / ``actions`` do not fit the
            env (the message names the field, both shapes and the fix).
    """
    if callable(getattr(demos, "to_continuous", None)):
        demos = demos.to_continuous()
    if not isinstance(demos, ContinuousDemonstrations):
        raise ValueError(
            f"demos must be ContinuousDemonstrations (states [m, T+1, N, d_s], actions "
            f"[m, T, N, d_a], lengths [m]) or convertible with to_continuous(), got "
            f"{type(demos).__name__}; wrap arrays with ContinuousDemonstrations(states=..., "
            f"actions=..., lengths=...) or record them with record_demonstrations.")
    if spec is None:
        return demos
    n, d_s = spec.state_shape
    if demos.states.shape[2:] != (n, d_s):
        raise ValueError(
            f"demonstrations field 'states' has per-step shape {list(demos.states.shape[2:])} "
            f"[N, d_s], but the env {spec.name} has joint states {[n, d_s]} "
            f"(info['state']); record them from the same game, with the same joint state "
            f"(JointAgentEnv's use_state = record_demonstrations' use_state).")
    if n * demos.action_dim != spec.action_dim:
        raise ValueError(
            f"demonstrations field 'actions' has per-step shape {list(demos.actions.shape[2:])} "
            f"[N, d_a], i.e. {n * demos.action_dim} values, but the env {spec.name}'s joint "
            f"action has {spec.action_dim} ({n} agents x {spec.action_dim // n}); record "
            f"each agent's action as the env takes it.")
    return demos
