"""Any PettingZoo ``ParallelEnv`` whose agents act in ``Box`` spaces as one gymnasium env,
so that a single-policy continuous-action solver (SB3's SAC, the constrained SAC
solver) can drive the whole team: :class:`JointAgentEnv`.

The joint action is the concatenation of the agents' (flattened) ``Box`` actions in
``possible_agents`` order; the joint observation is the concatenation of their
(flattened) observations, or a joint state (``env.state()`` or a function of the env).
The wrapper knows nothing of a particular game: it is what lets D-ICRL run on a
third-party game (issue 27; the first is mpe2's ``simple_spread``,
:mod:`dicrl_torch.envs.mpe`). A discrete-action game is refused before anything runs,
with the agent, its space and the fix named.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

StateFn = Callable[[ParallelEnv], Any]
RewardAggregator = Callable[[Mapping[str, float]], float]


def _sum_rewards(rewards: Mapping[str, float]) -> float:
    return float(sum(rewards.values()))


def _env_name(env: Any) -> str:
    meta = getattr(env, "metadata", None) or {}
    return str(meta.get("name", type(env).__name__))


def _flat_box(space: spaces.Box) -> tuple[np.ndarray, np.ndarray]:
    return (np.asarray(space.low, dtype=np.float64).ravel(),
            np.asarray(space.high, dtype=np.float64).ravel())


def _boxes(agents: list[str], space_of: Callable[[str], spaces.Space],
           problem: Callable[[str, spaces.Space], str]) -> list[spaces.Box]:
    """Every agent's space from ``space_of``; the first that is not a ``Box`` raises
    ``ValueError(problem(agent, space))``."""
    found = []
    for agent in agents:
        space = space_of(agent)
        if not isinstance(space, spaces.Box):
            raise ValueError(problem(agent, space))
        found.append(space)
    return found


def _joint_box(boxes: list[spaces.Box]) -> spaces.Box:
    """The concatenation of flattened boxes as one float32 ``Box``."""
    lows, highs = zip(*(_flat_box(b) for b in boxes), strict=True)
    return spaces.Box(low=np.concatenate(lows).astype(np.float32),
                      high=np.concatenate(highs).astype(np.float32), dtype=np.float32)


class JointAgentEnv(gym.Env):
    """A PettingZoo ``ParallelEnv`` with ``Box`` action spaces as one gymnasium env.

    With ``N`` agents in ``env.possible_agents`` order, agent ``i`` having an action
    box of ``a_i`` values and an observation box of ``o_i`` values (after flattening):

    - **action**: ``[sum_i a_i]`` float32, agent 0's action, then agent 1's, …; split
      back, reshaped to each agent's shape, clipped to its bounds and cast to its dtype.
      The part of an agent that is done (terminated or truncated) is ignored.
    - **observation**: ``"agents"`` (default): ``[sum_i o_i]`` float32, the agents'
      observations concatenated; a done agent's part is its last observation.
      ``"state"``: ``env.state()`` flattened, in ``env.state_space`` flattened (or the
      ``observation_space`` given). A callable ``state_fn(env) -> array``: its value
      flattened, in the ``observation_space`` given (required).
    - **reward**: ``reward_fn(rewards)`` of the dict of this step's per-agent rewards
      (default: their sum).
    - **terminated** when every agent is done and all of them terminated; **truncated**
      when every agent is done and some were truncated (e.g. the time limit).
    - **info**: ``agent_infos`` (agent → that agent's info of this step, ``{}`` for one
      that was already done), ``agent_rewards`` (agent → reward, for the agents that
      acted) and ``active`` (``[N]`` bool, agents not yet done after the step).

    Seeding passes through: ``reset(seed=s)`` seeds this env's ``np_random`` and resets
    the wrapped env with ``seed=s``; ``reset()`` without a seed continues the wrapped
    env's own stream. ``options`` go to the wrapped env's reset.

    Args:
        env: the ``ParallelEnv``; every agent of ``possible_agents`` must have a ``Box``
            action space (and, for ``observation="agents"``, a ``Box`` observation
            space).
        observation: ``"agents"``, ``"state"`` or a callable ``state_fn(env)``.
        observation_space: the joint observation's ``Box`` for a callable (required)
            or to replace ``env.state_space`` for ``"state"``; ignored for ``"agents"``.
        reward_fn: aggregates the per-agent rewards dict into the joint reward.

    Raises:
        TypeError: ``env`` is not a PettingZoo ``ParallelEnv``.
        ValueError: an agent's action space is not a ``Box`` (the message names the
            agent, the space and the fix), or the observation cannot be built.
    """

    def __init__(
        self,
        env: ParallelEnv,
        *,
        observation: str | StateFn = "agents",
        observation_space: spaces.Box | None = None,
        reward_fn: RewardAggregator | None = None,
    ) -> None:
        if not isinstance(env, ParallelEnv):
            raise TypeError(
                f"JointAgentEnv wraps a PettingZoo ParallelEnv, got {type(env).__name__}; "
                f"use the game's parallel_env(...) or convert an AEC env with "
                f"pettingzoo.utils.conversions.aec_to_parallel(env)."
            )
        agents = list(getattr(env, "possible_agents", []) or [])
        if not agents:
            raise ValueError(f"{_env_name(env)} has no possible_agents; JointAgentEnv needs "
                             f"the fixed list of agents to order the joint action.")
        self.env = env
        self.agent_order: list[str] = agents
        name = _env_name(env)
        action_boxes = _boxes(
            agents, env.action_space,
            lambda agent, space: f"JointAgentEnv needs a continuous (Box) action space for "
            f"every agent, but agent {agent!r} of {name} has {space!r}. Make the game with "
            f"continuous actions, e.g. mpe2's simple_spread_v3.parallel_env("
            f"continuous_actions=True), or wrap it so that it maps a Box action to its own.")
        self._action_boxes = action_boxes
        self._action_sizes = [int(np.prod(b.shape)) for b in action_boxes]
        self.action_space = _joint_box(action_boxes)

        self._state_fn: StateFn | None = None
        if isinstance(observation, str) and observation == "agents":
            boxes = _boxes(
                agents, env.observation_space,
                lambda agent, space: f"observation='agents' concatenates Box observations, "
                f"but agent {agent!r} of {name} has {space!r}; pass observation='state' or a "
                f"state_fn with its observation_space.")
            self._obs_sizes = [int(np.prod(b.shape)) for b in boxes]
            self.observation_space = _joint_box(boxes)
        elif isinstance(observation, str) and observation == "state":
            space = observation_space if observation_space is not None \
                else getattr(env, "state_space", None)
            if not callable(getattr(env, "state", None)) or not isinstance(space, spaces.Box):
                raise ValueError(
                    f"observation='state' needs env.state() and a Box env.state_space (or "
                    f"observation_space=Box(...)); {name} has state_space {space!r}."
                )
            self._state_fn = _env_state
            self.observation_space = _joint_box([space])
        elif callable(observation):
            if not isinstance(observation_space, spaces.Box):
                raise ValueError(
                    f"A state_fn observation needs observation_space=Box(...) for its "
                    f"values, got {observation_space!r}."
                )
            self._state_fn = observation
            self.observation_space = _joint_box([observation_space])
        else:
            raise ValueError(f"observation must be 'agents', 'state' or a callable "
                             f"state_fn(env), got {observation!r}.")
        if reward_fn is not None and not callable(reward_fn):
            raise ValueError(f"reward_fn must be callable (dict of per-agent rewards) -> "
                             f"float or None, got {type(reward_fn).__name__}.")
        self.reward_fn: RewardAggregator = reward_fn or _sum_rewards
        self.metadata = dict(getattr(env, "metadata", {}) or {})
        self.render_mode = getattr(env, "render_mode", None)
        self._last_obs: dict[str, np.ndarray] = {}
        self._ended: dict[str, str] = {}  # agent -> "terminated" | "truncated"
        self._started = False

    # ---- helpers ------------------------------------------------------------------
    def _joint_obs(self) -> np.ndarray:
        if self._state_fn is not None:
            value = np.asarray(self._state_fn(self.env), dtype=np.float32).ravel()
        else:
            value = np.concatenate([np.asarray(self._last_obs[a], dtype=np.float32).ravel()
                                    for a in self.agent_order])
        if value.shape != self.observation_space.shape:
            raise ValueError(f"The joint observation has shape {list(value.shape)}, but the "
                             f"observation space {list(self.observation_space.shape)}.")
        return value

    def _split_action(self, action: Any) -> dict[str, np.ndarray]:
        try:
            arr = np.asarray(action, dtype=np.float64)
        except (TypeError, ValueError):
            arr = None
        total = self.action_space.shape[0]
        if arr is None or arr.shape != (total,) or not np.all(np.isfinite(arr)):
            raise ValueError(
                f"action must be a finite [{total}] array: the agents' actions concatenated "
                f"in the order {self.agent_order} (sizes {self._action_sizes}); got {action!r}."
            )
        out, start = {}, 0
        for agent, box, size in zip(self.agent_order, self._action_boxes, self._action_sizes,
                                    strict=True):
            part = arr[start:start + size].reshape(box.shape)
            out[agent] = np.clip(part, box.low, box.high).astype(box.dtype)
            start += size
        return out

    def _active(self) -> np.ndarray:
        return np.array([a not in self._ended for a in self.agent_order])

    # ---- gymnasium API ------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None
              ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        obs, infos = self.env.reset(seed=seed, options=options)
        self._last_obs = dict(obs)
        missing = [a for a in self.agent_order if a not in self._last_obs]
        if self._state_fn is None and missing:
            raise ValueError(f"{_env_name(self.env)} gave no first observation for "
                             f"{missing}; observation='agents' needs every agent's.")
        live = set(self.env.agents)
        self._ended = {a: "absent" for a in self.agent_order if a not in live}
        self._started = True
        info = {"agent_infos": {a: infos.get(a, {}) for a in self.agent_order},
                "agent_rewards": {}, "active": self._active()}
        return self._joint_obs(), info

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if not self._started:
            raise RuntimeError("step() called before reset(); call env.reset(seed=...) first.")
        if not self.env.agents or len(self._ended) == len(self.agent_order):
            raise RuntimeError("The episode is over; call env.reset() before step().")
        split = self._split_action(action)
        obs, rewards, terms, truncs, infos = self.env.step(
            {a: split[a] for a in self.env.agents})
        self._last_obs.update(obs)
        for agent in self.agent_order:
            if agent in self._ended:
                continue
            if terms.get(agent, False):
                self._ended[agent] = "terminated"
            elif truncs.get(agent, False):
                self._ended[agent] = "truncated"
        over = not self.env.agents or len(self._ended) == len(self.agent_order)
        if over:  # an agent the env dropped without a flag ended with the episode
            for agent in self.agent_order:
                self._ended.setdefault(agent, "truncated")
        terminated = over and all(k in ("terminated", "absent") for k in self._ended.values())
        truncated = over and not terminated
        info = {"agent_infos": {a: infos.get(a, {}) for a in self.agent_order},
                "agent_rewards": {a: float(r) for a, r in rewards.items()},
                "active": self._active()}
        reward = float(self.reward_fn(rewards))
        return self._joint_obs(), reward, terminated, truncated, info

    def state(self) -> np.ndarray:
        """The wrapped env's ``state()``."""
        return self.env.state()

    def render(self) -> Any:
        return self.env.render()

    def close(self) -> None:
        self.env.close()


def _env_state(env: ParallelEnv) -> Any:
    return env.state()
