"""Any PettingZoo ``ParallelEnv`` whose agents act in ``Box`` spaces as one gymnasium env,
so that a single-policy continuous-action solver (SB3's SAC, the constrained SAC
solver) can drive the whole team: :class:`JointAgentEnv`.

The joint action is the concatenation of the agents' (flattened) ``Box`` actions in
``possible_agents`` order; the joint observation is the concatenation of their
(flattened) observations, or a joint state (``env.state()`` or a function of the env).
The wrapper knows nothing of a particular game: it is what lets D-ICRL run on a
third-party game (the first is mpe2's ``simple_spread``,
:mod:`dicrl_torch.envs.mpe`). A discrete-action game is refused before anything runs,
with the agent, its space and the fix named.

It is also a joint env as the constrained SAC solver drives one (the protocol of
:mod:`dicrl_torch.solvers.sac`): :attr:`JointAgentEnv.n_agents`, the joint state ``[N,
d_s]`` in ``info["state"]`` (:attr:`JointAgentEnv.state_shape`, read as
:func:`~dicrl_torch.demos.continuous.record_demonstrations` reads it), the agents'
``reached`` / ``violated`` flags, :meth:`JointAgentEnv.obs_from_states` and
:meth:`JointAgentEnv.set_rng`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from dicrl_torch.envs.parallel import CheckedParallelEnv

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


def agent_rows(state: Any, n_agents: int) -> np.ndarray | None:
    """A joint state as ``[N, d_s]`` float64 rows, one per agent: ``state`` itself when
    it is ``[N, d_s]``, a flat ``[N * d_s]`` (e.g. PettingZoo MPE's ``state()``, the
    agents concatenated) cut into ``N`` rows; None when it is neither."""
    s = np.asarray(state, dtype=np.float64)
    if s.ndim == 2 and s.shape[0] == n_agents:
        return s
    if s.ndim == 1 and s.size % n_agents == 0:
        return s.reshape(n_agents, -1)
    return None


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
      acted) and ``active`` (``[N]`` bool, agents not yet done after the step); and for
      a solver, ``reached`` and ``violated`` (``[N]`` bool: the agents whose info of
      this step says so; False where the game reports nothing) and ``state``.
    - **joint state** (``info["state"]``, also at the reset; :attr:`state_shape` ``(N,
      d_s)``): with ``use_state`` ``env.state()`` as ``[N, d_s]`` rows (a flat ``[N
      d_s]`` cut per agent), else the agents' (last) observations, each flattened,
      stacked. That is how :func:`~dicrl_torch.demos.continuous.record_demonstrations`
      reads a joint state, so demonstrations recorded from the same game with the same
      ``use_state`` hold the states a solver's rollouts see. :attr:`state_shape` is
      None (and ``info`` has no ``state``) when neither is possible (agents' widths
      differ).

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
        use_state: the joint state from ``env.state()`` (True), from the observations
            (False), or (None) from ``env.state()`` when the env has a ``Box``
            ``state_space`` that splits into ``N`` rows, else from the observations.

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
        use_state: bool | None = None,
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
        self.use_state, self.state_shape = self._joint_state_layout(use_state)
        self.n_agents: int = len(agents)
        # The observation is the flattened joint state exactly when both read the same
        # thing: env.state() for observation='state', the agents' observations for
        # 'agents'. Then obs_from_states can rebuild observations from recorded states.
        self._obs_is_state = self.state_shape is not None and (
            (observation == "state" and self.use_state)
            or (observation == "agents" and not self.use_state))
        self._observation_mode = observation if isinstance(observation, str) else "state_fn"
        self.metadata = dict(getattr(env, "metadata", {}) or {})
        self.render_mode = getattr(env, "render_mode", None)
        self._last_obs: dict[str, np.ndarray] = {}
        self._ended: dict[str, str] = {}  # agent -> "terminated" | "truncated"
        self._started = False

    # ---- helpers ------------------------------------------------------------------
    def _joint_state_layout(self, use_state: bool | None
                            ) -> tuple[bool, tuple[int, int] | None]:
        """``(use_state, state_shape)`` for the constructor's ``use_state``."""
        env, n, name = self.env, len(self.agent_order), _env_name(self.env)
        if use_state is not None and not isinstance(use_state, bool):
            raise ValueError(f"use_state must be True, False or None, got {use_state!r}.")
        space = getattr(env, "state_space", None)
        rows = None
        if callable(getattr(env, "state", None)) and isinstance(space, spaces.Box):
            rows = agent_rows(np.zeros(space.shape), n)
        if use_state and rows is None:
            raise ValueError(
                f"use_state=True needs env.state() and a Box env.state_space of shape [N, "
                f"d_s] or [N * d_s] for N={n} agents; {name} has state_space {space!r}. "
                f"Pass use_state=False to use the stacked observations.")
        if use_state or (use_state is None and rows is not None):
            return True, rows.shape
        sizes = set()
        for agent in self.agent_order:
            box = env.observation_space(agent)
            sizes.add(int(np.prod(box.shape)) if isinstance(box, spaces.Box) else -1)
        if len(sizes) == 1 and -1 not in sizes:
            return False, (n, sizes.pop())
        return False, None  # no joint state: the agents' observations differ in width

    def _joint_state(self) -> np.ndarray:
        """``[N, d_s]`` float64 joint state (class docstring)."""
        if self.use_state:
            rows = agent_rows(self.env.state(), self.n_agents)
            if rows is None or rows.shape != self.state_shape:
                raise ValueError(f"{_env_name(self.env)}.state() returned shape "
                                 f"{np.shape(self.env.state())}, not its state_space's "
                                 f"{list(self.state_shape)} rows; fix the env's state_space.")
            return rows
        missing = [a for a in self.agent_order if a not in self._last_obs]
        if missing:
            raise ValueError(f"{_env_name(self.env)} gave no observation for {missing}; a "
                             f"joint state of observations needs every agent's (or pass "
                             f"use_state=True).")
        return np.stack([np.asarray(self._last_obs[a], dtype=np.float64).ravel()
                         for a in self.agent_order])

    def _agent_flags(self, infos: Mapping[str, Any], key: str) -> np.ndarray:
        """``[N]`` bool: the agents whose info holds a true ``key``."""
        return np.array([bool((infos.get(a) or {}).get(key, False)) for a in self.agent_order])

    def _info(self, infos: Mapping[str, Any], rewards: Mapping[str, Any]) -> dict[str, Any]:
        info = {"agent_infos": {a: infos.get(a, {}) for a in self.agent_order},
                "agent_rewards": {a: float(r) for a, r in rewards.items()},
                "active": self._active(),
                "reached": self._agent_flags(infos, "reached"),
                "violated": self._agent_flags(infos, "violated")}
        if self.state_shape is not None:
            info["state"] = self._joint_state()
        return info

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
        return self._joint_obs(), self._info(infos, {})

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
        reward = float(self.reward_fn(rewards))
        return self._joint_obs(), reward, terminated, truncated, self._info(infos, rewards)

    def state(self) -> np.ndarray:
        """The wrapped env's ``state()``."""
        return self.env.state()

    # ---- the solver's joint-env protocol (dicrl_torch.solvers.sac) ----------------
    def obs_from_states(self, states: Any) -> np.ndarray:
        """The joint observations ``[..., obs_dim]`` float32 the policy sees in joint
        states ``[..., N, d_s]`` (e.g. demonstrations' ``states``): their flattening,
        which is what the observation is when it reads what the state reads
        (``observation="state"`` with ``use_state``, or ``"agents"`` without).

        Raises:
            ValueError: the observation is not the flattened state here (the message
                names the fix), or ``states`` do not have shape ``[..., N, d_s]``.
        """
        if not self._obs_is_state:
            raise ValueError(
                f"JointAgentEnv(observation={self._observation_mode!r}, use_state="
                f"{self.use_state}) cannot rebuild its observations from joint states "
                f"(needed to score or replay demonstrations): the observation is not the "
                f"flattened state. Wrap the game with observation='state' (and record "
                f"demonstrations with use_state=True), or observation='agents' with "
                f"use_state=False (and record with use_state=False).")
        s = np.asarray(states, dtype=np.float64)
        if s.ndim < 2 or s.shape[-2:] != tuple(self.state_shape):
            raise ValueError(f"states must have shape [..., {self.state_shape[0]}, "
                             f"{self.state_shape[1]}] (agents, state components), got "
                             f"{list(s.shape)}.")
        return s.reshape(*s.shape[:-2], -1).astype(np.float32)

    def set_rng(self, rng: np.random.Generator) -> None:
        """Draw the rest of this episode and the unseeded resets after it from ``rng``
        (a solver's clone gets streams of its own): the wrapped env's ``set_rng`` if it
        has one, else the stream of a
        :class:`~dicrl_torch.envs.parallel.CheckedParallelEnv` (``_rng``). Any other
        env keeps its own stream (a clone's copy of it goes on as the original's)."""
        if callable(getattr(self.env, "set_rng", None)):
            self.env.set_rng(rng)
        elif isinstance(self.env, CheckedParallelEnv):
            self.env._rng = rng

    def vector_env(self, n_envs: int) -> Any:
        """``n_envs`` episodes of this joint env stepped as one array computation (a
        :class:`~dicrl_torch.envs.vector.JointVectorEnv`, for the SAC solver's lean
        collection loop: :func:`~dicrl_torch.solvers.sac.env_list.vector_env_of`), or
        None, and the solver steps ``n_envs`` copies one by one
        (:class:`~dicrl_torch.solvers.sac.env_list.EnvList`).

        The wrapped game batches itself when it has ``joint_vector_env(n_envs)``; such a
        game's batched env gives the flattened joint state as observation, so it stands
        for this wrapper only when the observation is that (``observation="state"``
        with ``use_state``, in the same observation space). Otherwise None."""
        factory = getattr(self.env, "joint_vector_env", None)
        if not callable(factory) or self._observation_mode != "state" or not self.use_state:
            return None
        vec = factory(int(n_envs))
        # observation="state" with an observation_space of the caller's: its bounds
        # differ from the game's state_space, so the batched env would not match.
        if vec is not None and vec.observation_space != self.observation_space:
            vec.close()
            return None
        return vec

    def render(self) -> Any:
        return self.env.render()

    def close(self) -> None:
        self.env.close()


def _env_state(env: ParallelEnv) -> Any:
    return env.state()
