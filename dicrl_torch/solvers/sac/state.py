"""Exact, pickle-free state of the SAC solver's SB3 model and training envs.

:meth:`SACConstrainedSolver.state_dict` gathers, as plain data (tensors, python
scalars, strings, lists, dicts: what ``torch.load(..., weights_only=True)`` reads), all
that the next ``learn()`` reads: here the networks, optimisers and counters of the SB3
model (:func:`model_state_dict`) and the training envs in their current episodes
(:func:`vec_env_state_dict`); the replay buffer saves itself
(:meth:`FeatureReplayBuffer.state_dict`). SB3's own ``save`` pickles, so it is not used.

Each ``check_*`` function raises a ValueError naming the first field that does not fit
the object the state is loaded into, before anything is changed; each ``load_*`` sets
it.
"""

from __future__ import annotations

import copy
from collections import deque
from typing import Any

import numpy as np
import torch
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.vec_env import DummyVecEnv

from dicrl_torch.solvers.sac.randomness import generator_state_dict, restore_generator

__all__ = [
    "array_of",
    "check_model_state",
    "check_optional_array",
    "check_tensor",
    "check_vec_env_state",
    "load_model_state_dict",
    "load_vec_env_state_dict",
    "model_state_dict",
    "optional_array",
    "optional_tensor",
    "plain",
    "tensor_of",
    "torch_dtype",
    "vec_env_state_dict",
]

_FIX = "load a state saved by a solver built with the same arguments"


# ------------------------------------------------------------------ conversions
def tensor_of(a: Any) -> torch.Tensor:
    """A CPU tensor copy of the numpy array ``a``, of the same dtype."""
    return torch.from_numpy(np.array(a, copy=True))


def array_of(t: torch.Tensor) -> np.ndarray:
    """A numpy copy of ``t`` (the inverse of :func:`tensor_of`)."""
    return t.detach().cpu().numpy().copy()


def optional_tensor(a: Any) -> torch.Tensor | None:
    return None if a is None else tensor_of(a)


def optional_array(t: torch.Tensor | None) -> np.ndarray | None:
    return None if t is None else array_of(t)


def plain(value: Any) -> Any:
    """``value`` with numpy scalars as python ones, arrays as tensors and tuples and
    deques as lists, recursively (dicts keep their keys)."""
    if isinstance(value, dict):
        return {k: plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple | deque):
        return [plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return tensor_of(value)
    if isinstance(value, np.generic):
        return value.item()
    return value


def torch_dtype(np_dtype: Any) -> torch.dtype:
    """The torch dtype :func:`tensor_of` gives an array of ``np_dtype``."""
    return torch.from_numpy(np.empty(0, dtype=np_dtype)).dtype


def check_tensor(where: str, got: Any, shape: tuple[int, ...], dtype: torch.dtype) -> None:
    """A ValueError naming ``where`` unless ``got`` is a ``shape`` tensor of ``dtype``."""
    if not isinstance(got, torch.Tensor):
        raise ValueError(f"{where}: the state holds a {type(got).__name__}, not a tensor; "
                         f"{_FIX}.")
    if tuple(got.shape) != tuple(shape) or got.dtype != dtype:
        raise ValueError(f"{where}: the state holds shape {list(got.shape)} {got.dtype}, this "
                         f"solver {list(shape)} {dtype}; {_FIX}.")


def check_optional_array(where: str, got: Any, mine: np.ndarray | None) -> None:
    """As :func:`check_tensor` for ``mine``'s shape and dtype; None must match None."""
    if got is None or mine is None:
        if (got is None) != (mine is None):
            raise ValueError(f"{where}: the state holds {'no array' if got is None else 'an array'}"
                             f", this solver {'none' if mine is None else 'one'}; {_FIX}.")
        return
    check_tensor(where, got, mine.shape, torch_dtype(mine.dtype))


# ------------------------------------------------------------------ the SB3 model
_COUNTERS: tuple[tuple[str, str, type], ...] = (
    ("num_timesteps", "num_timesteps", int), ("n_updates", "_n_updates", int),
    ("episode_num", "_episode_num", int), ("total_timesteps", "_total_timesteps", int),
    ("num_timesteps_at_start", "_num_timesteps_at_start", int),
    ("current_progress_remaining", "_current_progress_remaining", float))
"""``(state key, SB3 attribute, type)`` of the model's counters."""
_LAST = ("last_obs", "last_original_obs", "last_episode_starts")
"""The model's ``_<key>`` arrays (None before the first ``learn()``)."""


def _optimizer_state(optimizer: torch.optim.Optimizer | None) -> dict[str, Any] | None:
    # A deep copy: Adam updates its moments in place.
    return None if optimizer is None else copy.deepcopy(optimizer.state_dict())


def model_state_dict(model: OffPolicyAlgorithm) -> dict[str, Any]:
    """Networks (actor, critics, target critics), optimisers (and the entropy
    coefficient's, if learned), SB3's counters, the last observations and episode
    starts, the episode statistics and the action space's random stream (warm-up
    actions) of ``model``; not its replay buffer."""
    if model.use_sde or model.action_noise is not None:
        raise ValueError("An exact state of SAC with gSDE exploration (use_sde) or an action "
                         "noise process is not supported: their noise lives outside the "
                         "networks and is not saved; drop them from sac_kwargs.")
    log_ent_coef = getattr(model, "log_ent_coef", None)
    return {
        "policy": {k: v.detach().clone() for k, v in model.policy.state_dict().items()},
        "actor_optimizer": _optimizer_state(model.actor.optimizer),
        "critic_optimizer": _optimizer_state(model.critic.optimizer),
        "log_ent_coef": None if log_ent_coef is None else log_ent_coef.detach().clone(),
        "ent_coef_optimizer": _optimizer_state(getattr(model, "ent_coef_optimizer", None)),
        **{key: kind(getattr(model, attr)) for key, attr, kind in _COUNTERS},
        **{key: optional_tensor(getattr(model, "_" + key)) for key in _LAST},
        "ep_info_buffer": None if model.ep_info_buffer is None else plain(model.ep_info_buffer),
        "ep_success_buffer": None if model.ep_success_buffer is None
        else plain(model.ep_success_buffer),
        "action_space_rng": generator_state_dict(model.action_space._np_random),
    }


def check_model_state(model: OffPolicyAlgorithm, sd: dict[str, Any]) -> None:
    """A ValueError naming the first network tensor (or entropy coefficient) of ``sd``
    whose name or shape differs from ``model``'s."""
    mine = model.policy.state_dict()
    theirs = sd["policy"]
    missing, unknown = sorted(set(mine) - set(theirs)), sorted(set(theirs) - set(mine))
    if missing or unknown:
        raise ValueError(f"SAC networks: the state lacks {missing[:4]} and has unknown "
                         f"{unknown[:4]} tensors (another network layout); {_FIX}.")
    for key, value in mine.items():
        check_tensor(f"SAC network tensor {key!r}", theirs[key], tuple(value.shape), value.dtype)
    log_ent_coef = getattr(model, "log_ent_coef", None)
    if (log_ent_coef is None) != (sd["log_ent_coef"] is None):
        raise ValueError(f"SAC entropy coefficient: the state's is "
                         f"{'fixed' if sd['log_ent_coef'] is None else 'learned'}, this "
                         f"solver's is {'fixed' if log_ent_coef is None else 'learned'}; {_FIX}.")
    for key in _LAST:
        if sd[key] is not None:
            want = _expected_last(model, key)
            check_tensor(f"SAC {key}", sd[key], want.shape, torch_dtype(want.dtype))


def _expected_last(model: OffPolicyAlgorithm, key: str) -> np.ndarray:
    """The shape and dtype ``model._<key>`` has once ``learn()`` has run."""
    n = model.n_envs
    if key == "last_episode_starts":
        return np.zeros((n,), dtype=bool)
    space = model.observation_space
    return np.zeros((n, *space.shape), dtype=space.dtype)


def load_model_state_dict(model: OffPolicyAlgorithm, sd: dict[str, Any]) -> None:
    """Set ``model`` to ``sd`` (checked first by :func:`check_model_state`)."""
    model.policy.load_state_dict(sd["policy"])  # copies into the optimisers' parameters
    model.actor.optimizer.load_state_dict(copy.deepcopy(sd["actor_optimizer"]))
    model.critic.optimizer.load_state_dict(copy.deepcopy(sd["critic_optimizer"]))
    if sd["log_ent_coef"] is not None:
        with torch.no_grad():
            model.log_ent_coef.copy_(sd["log_ent_coef"])
        model.ent_coef_optimizer.load_state_dict(copy.deepcopy(sd["ent_coef_optimizer"]))
    for key, attr, kind in _COUNTERS:
        setattr(model, attr, kind(sd[key]))
    for key in _LAST:
        setattr(model, "_" + key, optional_array(sd[key]))
    window = model._stats_window_size
    model.ep_info_buffer = None if sd["ep_info_buffer"] is None \
        else deque((dict(e) for e in sd["ep_info_buffer"]), maxlen=window)
    model.ep_success_buffer = None if sd["ep_success_buffer"] is None \
        else deque(sd["ep_success_buffer"], maxlen=window)
    model.action_space._np_random = restore_generator(model.action_space._np_random,
                                                      sd["action_space_rng"])


# ------------------------------------------------------------------ the training envs
_ARENA_ARRAYS: tuple[tuple[str, str], ...] = (
    ("state", "_state"), ("active", "_active"), ("violated", "violated"),
    ("reached", "reached"), ("overlay", "_overlay"))
"""``(state key, DroneArena attribute)`` of the arena's episode arrays (``_state`` and
``_overlay`` may be None)."""


def _monitored(env: Any) -> tuple[Monitor, Any]:
    """The Monitor wrapper that ``make_vec_env`` puts round each env, and the env."""
    if not isinstance(env, Monitor):
        raise ValueError(f"Expected a Monitor-wrapped env (as make_vec_env builds), got "
                         f"{type(env).__name__}.")
    return env, env.unwrapped


def _env_state(env: Any) -> dict[str, Any]:
    """One training env in its current episode: the Monitor's episode records, the
    joint env's last observation and random streams, and the arena's state and noise
    stream."""
    monitor, joint = _monitored(env)
    arena = joint.arena
    return {
        "monitor": {
            "rewards": [float(r) for r in monitor.rewards],
            "needs_reset": bool(monitor.needs_reset),
            "episode_returns": torch.tensor(monitor.episode_returns, dtype=torch.float64),
            "episode_lengths": torch.tensor(monitor.episode_lengths, dtype=torch.int64),
            "episode_times": torch.tensor(monitor.episode_times, dtype=torch.float64),
            "total_steps": int(monitor.total_steps),
            "t_start": float(monitor.t_start),
            "current_reset_info": plain(monitor.current_reset_info),
        },
        "obs": optional_tensor(joint._obs),
        "np_random": generator_state_dict(joint._np_random),
        "np_random_seed": None if joint._np_random_seed is None else int(joint._np_random_seed),
        "action_space_rng": generator_state_dict(joint.action_space._np_random),
        "observation_space_rng": generator_state_dict(joint.observation_space._np_random),
        "arena": {
            "agents": list(arena.agents),
            "timestep": int(arena.timestep),
            **{key: optional_tensor(getattr(arena, attr)) for key, attr in _ARENA_ARRAYS},
            "history": tensor_of(np.stack(arena._history)) if arena._history else None,
            "rng": generator_state_dict(arena._rng),
        },
    }


def vec_env_state_dict(vec_env: DummyVecEnv) -> dict[str, Any]:
    """The training ``DummyVecEnv``: the seeds and options of its next reset, its
    observation buffers and every env's :func:`_env_state`. (The per-step ``infos``
    buffers are rewritten before they are read, so they are not kept.)"""
    if not isinstance(vec_env, DummyVecEnv) or list(vec_env.keys) != [None]:
        raise ValueError("Only a DummyVecEnv with a Box observation space is supported.")
    return {
        "n_envs": int(vec_env.num_envs),
        "seeds": [None if s is None else int(s) for s in vec_env._seeds],
        "options": plain(vec_env._options),
        "buf_obs": tensor_of(vec_env.buf_obs[None]),
        "buf_dones": tensor_of(vec_env.buf_dones),
        "buf_rews": tensor_of(vec_env.buf_rews),
        "envs": [_env_state(env) for env in vec_env.envs],
    }


def check_vec_env_state(vec_env: DummyVecEnv, sd: dict[str, Any]) -> None:
    """A ValueError unless ``sd`` holds as many envs, of the same observation shape."""
    if int(sd["n_envs"]) != vec_env.num_envs or len(sd["envs"]) != vec_env.num_envs:
        raise ValueError(f"training envs: the state holds {sd['n_envs']}, this solver "
                         f"{vec_env.num_envs} (n_envs); {_FIX}.")
    obs = vec_env.buf_obs[None]
    check_tensor("training envs' observation buffer", sd["buf_obs"], obs.shape,
                 torch_dtype(obs.dtype))
    for k, (env, state) in enumerate(zip(vec_env.envs, sd["envs"], strict=True)):
        _, joint = _monitored(env)
        shape = joint.observation_space.shape
        if state["obs"] is not None:
            check_tensor(f"training env {k}'s observation", state["obs"], shape,
                         torch_dtype(joint.observation_space.dtype))
        if state["arena"]["state"] is not None:
            check_tensor(f"training env {k}'s arena state", state["arena"]["state"],
                         (len(joint.arena.possible_agents), 4), torch.float64)


def load_vec_env_state_dict(vec_env: DummyVecEnv, sd: dict[str, Any]) -> None:
    """Set the training envs to ``sd`` (checked first by :func:`check_vec_env_state`)."""
    vec_env._seeds = list(sd["seeds"])
    vec_env._options = copy.deepcopy(sd["options"])
    vec_env.buf_obs[None][...] = array_of(sd["buf_obs"])
    vec_env.buf_dones[...] = array_of(sd["buf_dones"])
    vec_env.buf_rews[...] = array_of(sd["buf_rews"])
    for env, state in zip(vec_env.envs, sd["envs"], strict=True):
        monitor, joint = _monitored(env)
        m = state["monitor"]
        monitor.rewards = [float(r) for r in m["rewards"]]
        monitor.needs_reset = bool(m["needs_reset"])
        monitor.episode_returns = m["episode_returns"].tolist()
        monitor.episode_lengths = m["episode_lengths"].tolist()
        monitor.episode_times = m["episode_times"].tolist()
        monitor.total_steps = int(m["total_steps"])
        monitor.t_start = float(m["t_start"])
        monitor.current_reset_info = copy.deepcopy(m["current_reset_info"])
        joint._obs = optional_array(state["obs"])
        joint._np_random = restore_generator(joint._np_random, state["np_random"])
        joint._np_random_seed = state["np_random_seed"]
        joint.action_space._np_random = restore_generator(joint.action_space._np_random,
                                                          state["action_space_rng"])
        joint.observation_space._np_random = restore_generator(
            joint.observation_space._np_random, state["observation_space_rng"])
        a, arena = state["arena"], joint.arena
        arena.agents = list(a["agents"])
        arena.timestep = int(a["timestep"])
        for key, attr in _ARENA_ARRAYS:
            setattr(arena, attr, optional_array(a[key]))
        arena._history = [] if a["history"] is None else list(array_of(a["history"]))
        arena._rng = restore_generator(arena._rng, a["rng"])
