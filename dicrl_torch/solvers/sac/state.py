"""Exact, pickle-free state of the SAC solver's SB3 model and training envs.

:meth:`SACConstrainedSolver.state_dict` gathers, as plain data (tensors, python
scalars, strings, lists, dicts: what ``torch.load(..., weights_only=True)`` reads), all
that the next ``learn()`` reads: here the networks, optimisers and counters of the SB3
model (:func:`model_state_dict`) and the training envs in their current episodes
(:func:`vec_env_state_dict`: any env, through :func:`object_state_dict` unless it saves
itself); the replay buffer saves itself (:meth:`FeatureReplayBuffer.state_dict`). SB3's
own ``save`` pickles, so it is not used.

Each ``check_*`` function raises a ValueError naming the first field that does not fit
the object the state is loaded into, before anything is changed; each ``load_*`` sets
it.
"""

from __future__ import annotations

import copy
import functools
import types
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
    "env_state_dict",
    "load_env_state_dict",
    "load_model_state_dict",
    "load_object_state_dict",
    "load_vec_env_state_dict",
    "model_state_dict",
    "object_state_dict",
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


# ------------------------------------------------------------------ any env's attributes
# Values that are part of how an object was built, not of its state: not saved, kept
# as the fresh object has them (bound methods patched in, callbacks, dtypes).
_CONSTANT_TYPES = (types.FunctionType, types.MethodType, types.BuiltinFunctionType,
                   types.BuiltinMethodType, types.ModuleType, type, functools.partial,
                   np.dtype)


def object_state_dict(obj: Any) -> dict[str, Any]:
    """Every attribute of ``obj``, recursively, as plain data: a game of any kind, mid
    episode, saved without pickling and without code of its own.

    It walks the instance attributes (``vars``) of ``obj`` and of every object they
    hold, and encodes numpy arrays and scalars, tensors, numpy ``Generator`` s and
    ``RandomState`` s, lists, tuples and dicts (of plain keys), and python scalars and
    strings; functions, bound methods, classes, modules and dtypes are construction
    constants and are kept as the loading object has them. An object reached twice is
    saved once (a cycle or a shared reference). Anything else raises a ValueError naming
    its path and the fix.

    :func:`load_object_state_dict` sets the attributes of an object built the same way
    (the same classes along every path) in place, so references into it stay valid.
    """
    return _encode(obj, type(obj).__name__, set())


def _encode(value: Any, path: str, seen: set[int]) -> Any:
    # numpy scalars first: np.float64 is a float, np.int64 is not an int.
    if isinstance(value, np.generic):
        return {"kind": "numpy_scalar", "dtype": str(value.dtype), "value": value.item()}
    if value is None or isinstance(value, bool | int | float | str):
        return value
    if isinstance(value, np.ndarray):
        if value.dtype.kind not in "biuf":
            raise ValueError(f"{path}: a numpy array of dtype {value.dtype} cannot be saved "
                             f"as a tensor; {_ENV_FIX}.")
        return {"kind": "ndarray", "value": tensor_of(value)}
    if isinstance(value, torch.Tensor):
        return {"kind": "tensor", "value": value.detach().cpu().clone()}
    if isinstance(value, np.random.Generator):
        return {"kind": "generator", "state": generator_state_dict(value)}
    if isinstance(value, np.random.RandomState):
        return {"kind": "random_state", "state": plain(value.get_state(legacy=False))}
    if isinstance(value, _CONSTANT_TYPES):
        return {"kind": "constant"}
    if isinstance(value, tuple):  # immutable: rebuilt on loading, never shared state
        return {"kind": "tuple", "items": [_encode(v, f"{path}[{i}]", seen)
                                           for i, v in enumerate(value)]}
    if id(value) in seen:
        return {"kind": "seen"}
    seen.add(id(value))
    if isinstance(value, list):
        return {"kind": "list", "items": [_encode(v, f"{path}[{i}]", seen)
                                          for i, v in enumerate(value)]}
    if isinstance(value, dict):
        bad = [k for k in value if not (k is None or isinstance(k, bool | int | float | str))]
        if bad:
            raise ValueError(f"{path}: a dict key {bad[0]!r} is not a plain value; "
                             f"{_ENV_FIX}.")
        return {"kind": "dict", "keys": list(value),
                "values": [_encode(v, f"{path}[{k!r}]", seen) for k, v in value.items()]}
    if hasattr(value, "__dict__"):
        return {"kind": "object", "type": type(value).__qualname__,
                "attrs": {k: _encode(v, f"{path}.{k}", seen) for k, v in vars(value).items()}}
    raise ValueError(f"{path}: a {type(value).__name__} cannot be saved as plain data; "
                     f"{_ENV_FIX}.")


def _arrays(value: Any) -> Any:
    """Tensors back to numpy arrays, recursively through dicts (the inverse of
    :func:`plain` on a ``RandomState``'s state)."""
    if isinstance(value, dict):
        return {k: _arrays(v) for k, v in value.items()}
    return array_of(value) if isinstance(value, torch.Tensor) else value


def load_object_state_dict(obj: Any, sd: dict[str, Any]) -> None:
    """Set ``obj`` to an :func:`object_state_dict` (attributes it lacks then are
    removed, objects are updated in place). A ValueError names the first path whose
    object differs in kind; call it on a copy first to leave ``obj`` untouched then."""
    _decode(obj, sd, type(obj).__name__)


def _decode(current: Any, data: Any, path: str) -> Any:
    """The value ``data`` encodes; objects, lists and dicts are ``current``'s own,
    updated in place."""
    if not isinstance(data, dict):
        return data
    kind = data["kind"]
    if kind == "numpy_scalar":
        return np.dtype(data["dtype"]).type(data["value"])
    if kind == "ndarray":
        return array_of(data["value"])
    if kind == "tensor":
        device = current.device if isinstance(current, torch.Tensor) else "cpu"
        return data["value"].clone().to(device)
    if kind == "generator":
        return restore_generator(current if isinstance(current, np.random.Generator)
                                 else None, data["state"])
    if kind == "random_state":
        rs = current if isinstance(current, np.random.RandomState) else np.random.RandomState()
        rs.set_state(_arrays(data["state"]))
        return rs
    if kind in ("constant", "seen"):
        return current
    if kind == "tuple":
        old = current if isinstance(current, tuple) else ()
        return tuple(_decode(old[i] if i < len(old) else None, d, f"{path}[{i}]")
                     for i, d in enumerate(data["items"]))
    if kind == "list":
        old = current if isinstance(current, list) else []
        items = [_decode(old[i] if i < len(old) else None, d, f"{path}[{i}]")
                 for i, d in enumerate(data["items"])]
        if isinstance(current, list):
            current[:] = items
            return current
        return items
    if kind == "dict":
        old = current if isinstance(current, dict) else {}
        items = {k: _decode(old.get(k), d, f"{path}[{k!r}]")
                 for k, d in zip(data["keys"], data["values"], strict=True)}
        if isinstance(current, dict):
            current.clear()
            current.update(items)
            return current
        return items
    if kind == "object":
        if current is None or type(current).__qualname__ != data["type"]:
            raise ValueError(f"{path}: the state holds a {data['type']}, this env "
                             f"{type(current).__name__}; {_FIX}.")
        attrs = vars(current)
        for name, d in data["attrs"].items():
            # Straight into the instance dict: frozen dataclasses and property setters
            # are bypassed, as the value is exactly one the object held before.
            attrs[name] = _decode(attrs.get(name), d, f"{path}.{name}")
        for name in [k for k in attrs if k not in data["attrs"]]:
            del attrs[name]  # set after the save (e.g. at a later reset): not then
        return current
    raise ValueError(f"{path}: unknown kind {kind!r} in the state; {_FIX}.")


# ------------------------------------------------------------------ the training envs
_ENV_FIX = ("give the env (or the game it wraps) state_dict() and load_state_dict() "
            "methods of its own, or keep it to numpy / torch / python data")


def _monitored(env: Any) -> tuple[Monitor, Any]:
    """The Monitor wrapper that ``make_vec_env`` puts round each env, and the env the
    solver's ``env_factory`` built."""
    if not isinstance(env, Monitor):
        raise ValueError(f"Expected a Monitor-wrapped env (as make_vec_env builds), got "
                         f"{type(env).__name__}.")
    return env, env.env


def env_state_dict(env: Any) -> dict[str, Any]:
    """One env in its current episode as plain data: its own ``state_dict()`` if it has
    one, else :func:`object_state_dict` of all its attributes (its ``np_random``, its
    spaces' streams, the game it wraps and that game's state and streams)."""
    own = getattr(env, "state_dict", None)
    return own() if callable(own) else object_state_dict(env)


def load_env_state_dict(env: Any, sd: dict[str, Any]) -> None:
    """Set ``env`` to an :func:`env_state_dict` (its own ``load_state_dict`` if it has
    one)."""
    own = getattr(env, "load_state_dict", None)
    if callable(own):
        own(sd)
    else:
        load_object_state_dict(env, sd)


def _env_state(env: Any) -> dict[str, Any]:
    """One training env in its current episode: the Monitor's episode records and the
    env's :func:`env_state_dict`."""
    monitor, joint = _monitored(env)
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
        "env": env_state_dict(joint),
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
    """A ValueError unless ``sd`` holds as many envs, of the same observation shape,
    each loadable into a copy of the env it would replace."""
    if int(sd["n_envs"]) != vec_env.num_envs or len(sd["envs"]) != vec_env.num_envs:
        raise ValueError(f"training envs: the state holds {sd['n_envs']}, this solver "
                         f"{vec_env.num_envs} (n_envs); {_FIX}.")
    obs = vec_env.buf_obs[None]
    check_tensor("training envs' observation buffer", sd["buf_obs"], obs.shape,
                 torch_dtype(obs.dtype))
    for k, (env, state) in enumerate(zip(vec_env.envs, sd["envs"], strict=True)):
        _, joint = _monitored(env)
        try:
            load_env_state_dict(copy.deepcopy(joint), state["env"])
        except ValueError as e:
            raise ValueError(f"training env {k}: {e}") from None


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
        load_env_state_dict(joint, state["env"])
