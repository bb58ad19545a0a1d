"""Demonstrations of any continuous multi-agent environment: one validated ``.npz``
format, and a recorder for any PettingZoo ``ParallelEnv``.

Users who bring their own environment, experts and feature networks hand their
trajectories to the library in this one format. A set of ``m`` episodes of ``N`` agents
is:

- ``states [m, T+1, N, d_s]`` float: per agent its state (or observation) at each time,
  ``states[k, 0]`` after the reset, ``states[k, t+1]`` after step ``t``;
- ``actions [m, T, N, d_a]`` float: per agent its action at step ``t``;
- ``lengths [m]`` int in ``[1, T]``: how many steps episode ``k`` took. Episodes may end
  early; ``T`` is the longest. Entries past an episode's end (``states[k, L+1:]``,
  ``actions[k, L:]``) are padding: they are never validated (NaN is allowed there on
  input) and :class:`ContinuousDemonstrations` overwrites them with the episode's last
  state and zero actions, so that the stored arrays are NaN-free and two sets that
  differ only in their padding are equal;
- optionally ``agent_names [N]`` (str), ``seeds [m]`` (int, each episode's reset seed)
  and ``agent_lengths [m, N]`` (int in ``[0, lengths[k]]``: the steps agent ``i`` acted
  in episode ``k``; after them it had left the episode, e.g. arrived or frozen, and its
  recorded actions, ignored by the env, are not its choices). Without it every agent
  acts for the whole episode.

On disk it is an ``.npz`` archive (plus ``format_version``) written atomically by
:func:`save_continuous_demonstrations` and read by :func:`load_continuous_demonstrations`
with ``allow_pickle=False``, checked against the schema: every refusal names the file,
the field, what was found, what was expected and the fix (the house style of
:mod:`dicrl_torch.demos.storage` and :mod:`dicrl_torch.demos.drone_demos`).

:func:`record_demonstrations` records episodes from any ``ParallelEnv`` and any policy,
a planner or a trained network alike.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from numpy.typing import ArrayLike

from dicrl_torch.demos.npz import (
    check_expected,
    check_float_dtype,
    check_lengths,
    check_ndim,
    check_seeds,
    frozen,
    is_int,
    open_archive,
    pad_episodes,
    read_field,
    refuse_first,
    save_archive,
)
from dicrl_torch.demos.trajectories import TrajectoryArrays
from dicrl_torch.envs.joint import agent_rows

__all__ = [
    "FORMAT_VERSION",
    "ContinuousDemonstrations",
    "Policy",
    "load_continuous_demonstrations",
    "record_demonstrations",
    "save_continuous_demonstrations",
    "validate_continuous_arrays",
]

FORMAT_VERSION = 1
ARRAY_FIELDS: tuple[str, ...] = ("states", "actions", "lengths")
FIELDS: tuple[str, ...] = ARRAY_FIELDS + ("format_version",)
OPTIONAL_FIELDS: tuple[str, ...] = ("agent_names", "seeds", "agent_lengths")

Policy = Callable[[dict[str, Any], Any], Mapping[str, Any]]
"""``policy(observations, env) -> actions``: the live agents' (``env.agents``)
observations, a dict keyed by agent name as ``env.reset`` / ``env.step`` return them,
and the env itself (a planner may read its true state) to a dict of one action per live
agent."""

_FIX = "save_continuous_demonstrations"


def _valid_steps(lengths: np.ndarray, steps: int) -> np.ndarray:
    """``[m, steps]`` bool: True for ``t < lengths[k]``."""
    return np.arange(steps)[None, :] < lengths[:, None]


def _check_finite_in_episodes(a: np.ndarray, lengths: np.ndarray, field: str,
                              source: str) -> None:
    """Every entry of ``a [m, t, N, d]`` inside an episode is finite (``t <= lengths[k]``
    for states, ``t < lengths[k]`` for actions); the padding after it is not looked at."""
    extra = 1 if field == "states" else 0
    bad = ~np.isfinite(a) & _valid_steps(lengths + extra, a.shape[1])[:, :, None, None]
    refuse_first(bad, lambda k, t, i, c: (
        f"{source}: field '{field}' holds {a[k, t, i, c]} at (episode={k}, time={t}, "
        f"agent={i}, component={c}), inside the episode (lengths[{k}] = "
        f"{int(lengths[k])} steps); demonstrations must be finite up to their end. "
        f"Re-record the episode, or end it earlier with its 'lengths' entry (entries "
        f"after the end are padding and may hold anything)."))


def validate_continuous_arrays(
    states: ArrayLike, actions: ArrayLike, lengths: ArrayLike,
    agent_names: ArrayLike | None = None, seeds: ArrayLike | None = None,
    agent_lengths: ArrayLike | None = None, *, source: str,
) -> None:
    """Check continuous demonstration arrays against the schema; raise ``ValueError``
    if not.

    Args:
        states: ``[m, T+1, N, d_s]`` float, ``m, T, N, d_s >= 1``; finite up to each
            episode's end (``states[k, :lengths[k]+1]``).
        actions: ``[m, T, N, d_a]`` float, ``d_a >= 1``; finite up to each episode's end
            (``actions[k, :lengths[k]]``).
        lengths: ``[m]`` int in ``[1, T]``.
        agent_names: None or ``N`` distinct non-empty strings.
        seeds: None or ``[m]`` non-negative ints.
        agent_lengths: None or ``[m, N]`` ints, ``agent_lengths[k, i]`` in
            ``[0, lengths[k]]``.
        source: what the arrays came from, put at the start of every message.

    Raises:
        ValueError: naming ``source``, the offending field, what it holds, what was
            expected and the fix.
    """
    states, actions, lengths = np.asarray(states), np.asarray(actions), np.asarray(lengths)
    check_float_dtype(states, "states", source)
    check_float_dtype(actions, "actions", source)
    check_ndim(states, "states", 4, "[m, T+1, N, d_s] (episodes, times, agents, state "
               "components)", source, hint="; give a single agent or a scalar state an axis "
               "of size 1 (e.g. `states[..., None]`)")
    m, t1, n, d_s = states.shape
    if m < 1 or t1 < 2 or n < 1 or d_s < 1:
        raise ValueError(
            f"{source}: field 'states' has shape {states.shape} = [m, T+1, N, d_s], but "
            f"needs m >= 1 episodes, T+1 >= 2 times, N >= 1 agents and d_s >= 1 "
            f"components; record at least one step of one episode.")
    check_ndim(actions, "actions", 4, "[m, T, N, d_a]", source,
               hint="; give a scalar action an axis of size 1 (e.g. `actions[..., None]`)")
    # One message per disagreeing axis, so the user knows which array is off.
    for axis, what, want in ((0, "episodes m", m), (1, "steps T", t1 - 1), (2, "agents N", n)):
        if actions.shape[axis] != want:
            raise ValueError(
                f"{source}: field 'actions' has shape {actions.shape}, i.e. "
                f"{actions.shape[axis]} {what}, but 'states' {states.shape} = [m, T+1, N, "
                f"d_s] has {want}; actions must have shape {(m, t1 - 1, n, '*')} = "
                f"[m, T, N, d_a] (one action per agent and step, one state more than "
                f"actions per episode).")
    if actions.shape[3] < 1:
        raise ValueError(f"{source}: field 'actions' has shape {actions.shape}: d_a = 0; "
                         f"each action needs at least one component.")
    check_lengths(lengths, m, t1 - 1, source, "episode")
    _check_finite_in_episodes(states, lengths, "states", source)
    _check_finite_in_episodes(actions, lengths, "actions", source)
    if agent_names is not None:
        names = np.asarray(agent_names)
        if names.dtype.kind != "U" or names.shape != (n,):
            raise ValueError(
                f"{source}: field 'agent_names' must be {n} strings (one per agent of "
                f"'states'), got dtype {names.dtype} shape {names.shape}; pass e.g. "
                f"`np.array(env.possible_agents, dtype=str)` or leave it out.")
        empty = [i for i, s in enumerate(names.tolist()) if not s]
        dupes = sorted({s for s in names.tolist() if names.tolist().count(s) > 1})
        if empty or dupes:
            raise ValueError(
                f"{source}: field 'agent_names' must be distinct non-empty names, got "
                f"{names.tolist()} (empty at {empty}, repeated {dupes}); rename the agents.")
    check_seeds(seeds, m, source, "episode")
    if agent_lengths is not None:
        acted = np.asarray(agent_lengths)
        if not np.issubdtype(acted.dtype, np.integer) or acted.shape != (m, n):
            raise ValueError(
                f"{source}: field 'agent_lengths' must be ints of shape ({m}, {n}) (per "
                f"episode and agent the steps it acted), got dtype {acted.dtype} shape "
                f"{acted.shape}; store `agent_lengths.astype(np.int64)` or leave it out "
                f"(every agent then acts for the whole episode).")
        refuse_first((acted < 0) | (acted > lengths[:, None]), lambda k, i: (
            f"{source}: field 'agent_lengths' holds {int(acted[k, i])} for episode {k}, "
            f"agent {i}, outside [0, lengths[{k}] = {int(lengths[k])}]: an agent acts for "
            f"at most the steps of its episode. Fix the entry or leave the field out."))


@dataclass(frozen=True, eq=False, repr=False)
class ContinuousDemonstrations(TrajectoryArrays):
    """Episodes of ``N`` agents in a continuous environment, validated on construction (a
    :class:`~dicrl_torch.demos.trajectories.Trajectories`; equal by content, subsets
    with :meth:`subset`, split over learners by
    :func:`~dicrl_torch.demos.partition.partition_demonstrations`).

    The arrays are copied read-only (float64, int64) and their padding is overwritten
    (states past an episode's end repeat its last state, actions there are 0), so the
    object is immutable and NaN-free.

    Args:
        states: ``[m, T+1, N, d_s]`` per agent state or observation.
        actions: ``[m, T, N, d_a]`` per agent action.
        lengths: ``[m]`` steps of each episode, in ``[1, T]``.
        agent_names: optional ``N`` agent names (e.g. ``env.possible_agents``).
        seeds: optional ``[m]`` reset seed of each episode.
        agent_lengths: optional ``[m, N]`` steps each agent acted (module docstring);
            stored as None when every agent acted for its whole episode, so that the
            two ways of saying so are equal.
    """

    states: np.ndarray
    actions: np.ndarray
    lengths: np.ndarray
    agent_names: tuple[str, ...] | None = None
    seeds: np.ndarray | None = None
    agent_lengths: np.ndarray | None = None

    per_trajectory: ClassVar[tuple[str, ...]] = ("states", "actions", "lengths", "seeds",
                                                 "agent_lengths")
    unit: ClassVar[str] = "episodes"

    def __post_init__(self) -> None:
        validate_continuous_arrays(self.states, self.actions, self.lengths,
                                   self.agent_names, self.seeds, self.agent_lengths,
                                   source="ContinuousDemonstrations")
        lengths = frozen(self.lengths, np.int64)
        # Canonical padding: downstream code may evaluate features on the whole padded
        # array (masking afterwards), so it must never meet a NaN there. Past its end an
        # episode repeats its last state (time min(t, L)) and takes zero actions.
        states, actions = np.asarray(self.states), np.asarray(self.actions)
        last = np.minimum(np.arange(states.shape[1]), lengths[:, None])  # [m, T+1]
        states = np.take_along_axis(states, last[:, :, None, None], axis=1)
        taken = _valid_steps(lengths, actions.shape[1])[:, :, None, None]
        actions = np.where(taken, actions, 0.0)
        object.__setattr__(self, "states", frozen(states, np.float64))
        object.__setattr__(self, "actions", frozen(actions, np.float64))
        object.__setattr__(self, "lengths", lengths)
        if self.agent_names is not None:
            object.__setattr__(self, "agent_names",
                               tuple(str(s) for s in np.asarray(self.agent_names).tolist()))
        if self.seeds is not None:
            object.__setattr__(self, "seeds", frozen(self.seeds, np.int64))
        if self.agent_lengths is not None:
            acted = np.asarray(self.agent_lengths)
            whole = bool((acted == lengths[:, None]).all())
            object.__setattr__(self, "agent_lengths",
                               None if whole else frozen(acted, np.int64))

    @property
    def n_episodes(self) -> int:
        """``m`` (:attr:`n_trajectories`)."""
        return self.n_trajectories

    @property
    def n_agents(self) -> int:
        """``N``."""
        return self.states.shape[2]

    @property
    def state_dim(self) -> int:
        """``d_s``, the components of one agent's state."""
        return self.states.shape[3]

    @property
    def action_dim(self) -> int:
        """``d_a``, the components of one agent's action."""
        return self.actions.shape[3]

    def step_mask(self) -> np.ndarray:
        """``[m, T]`` bool: True for the steps ``t < lengths[k]`` that episode ``k``
        took; a sum over ``(states[:, t], actions[:, t])`` pairs weights by it."""
        return _valid_steps(self.lengths, self.horizon)

    def acting_mask(self) -> np.ndarray:
        """``[m, T, N]`` bool: True where agent ``i`` acted at step ``t`` of episode
        ``k`` (``t < agent_lengths[k, i]``, or ``t < lengths[k]`` without them); a
        likelihood of the actions counts only these."""
        acted = (np.broadcast_to(self.lengths[:, None], (self.n_episodes, self.n_agents))
                 if self.agent_lengths is None else self.agent_lengths)
        return np.arange(self.horizon)[None, :, None] < acted[:, None, :]

    def state_mask(self) -> np.ndarray:
        """``[m, T+1]`` bool: True for the states ``t <= lengths[k]`` of episode ``k``."""
        return _valid_steps(self.lengths + 1, self.horizon + 1)

    def episode(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Episode ``k`` without padding: ``states [L+1, N, d_s]`` and ``actions [L, N,
        d_a]`` with ``L = lengths[k]`` (read-only views)."""
        n = int(self.lengths[k])
        return self.states[k, :n + 1], self.actions[k, :n]

    def __repr__(self) -> str:
        return (f"ContinuousDemonstrations(m={self.n_episodes}, T={self.horizon}, "
                f"N={self.n_agents}, d_s={self.state_dim}, d_a={self.action_dim})")


# ================================================================================ disk
def _archive_fields(demos: ContinuousDemonstrations) -> dict[str, np.ndarray | None]:
    names = demos.agent_names
    return {"states": demos.states, "actions": demos.actions, "lengths": demos.lengths,
            "format_version": np.int64(FORMAT_VERSION),
            # A fixed-width unicode array: it loads without pickle, unlike a list of str.
            "agent_names": None if names is None else np.array(names, dtype=np.str_),
            "seeds": demos.seeds, "agent_lengths": demos.agent_lengths}


def save_continuous_demonstrations(
    path: str | os.PathLike[str], demos: ContinuousDemonstrations
) -> Path:
    """Write ``demos`` to ``path`` for :func:`load_continuous_demonstrations`: a compressed
    ``.npz``, written atomically by :func:`~dicrl_torch.demos.npz.save_archive` (no
    suffix is appended, parent directories are created); return the path."""
    return save_archive(
        path, demos, ContinuousDemonstrations, fields=_archive_fields,
        writer="save_continuous_demonstrations",
        how="wrap the arrays with ContinuousDemonstrations(states=..., actions=..., "
            "lengths=...) or record them with record_demonstrations(env, policy, ...)")


def load_continuous_demonstrations(
    path: str | os.PathLike[str], *, n_agents: int | None = None,
    state_dim: int | None = None, action_dim: int | None = None, horizon: int | None = None,
) -> ContinuousDemonstrations:
    """Read demonstrations written by :func:`save_continuous_demonstrations`, never
    unpickling.

    Args:
        path: the ``.npz`` file.
        n_agents, state_dim, action_dim, horizon: when given (the environment's ``N``,
            ``d_s``, ``d_a`` and ``T``), the file must have been made for exactly these.

    Returns:
        The validated demonstrations.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: the file is not a valid continuous demonstrations archive, or it
            disagrees with the given dimensions; the message names the file, the field,
            what was found, what was expected and the fix.
    """
    path = Path(path)
    source = f"continuous demonstrations file '{path}'"
    with open_archive(path, source=source, required=FIELDS, optional=OPTIONAL_FIELDS,
                      version=FORMAT_VERSION, fix=_FIX,
                      generate="Record the demonstrations first (record_demonstrations, "
                               "then save_continuous_demonstrations)") as archive:
        arrays = {f: read_field(archive, f, source, _FIX) for f in ARRAY_FIELDS}
        extra = {f: read_field(archive, f, source, _FIX) if f in archive.files else None
                 for f in OPTIONAL_FIELDS}
    # Validate here, not only in ContinuousDemonstrations, so the messages name the file.
    validate_continuous_arrays(**arrays, **extra, source=source)
    states, actions = arrays["states"], arrays["actions"]
    check_expected(source, {"n_agents": states.shape[2], "state_dim": states.shape[3],
                            "action_dim": actions.shape[3], "horizon": actions.shape[1]},
                   {"n_agents": n_agents, "state_dim": state_dim, "action_dim": action_dim,
                    "horizon": horizon})
    return ContinuousDemonstrations(**arrays, **extra)


# ============================================================================ recorder
def _as_vector(x: Any, what: str) -> np.ndarray:
    try:
        v = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise TypeError(f"record_demonstrations: {what} is not numeric ({type(x).__name__}: "
                        f"{e}); record envs whose observations and actions are arrays.") from e
    return v.reshape(-1)


def _stack(vectors: Sequence[np.ndarray], what: str) -> np.ndarray:
    sizes = {v.size for v in vectors}
    if len(sizes) != 1:
        raise ValueError(
            f"record_demonstrations: the agents' {what} have different sizes "
            f"{[v.size for v in vectors]}; the format stores [N, d] per step, so every "
            f"agent needs the same width (pad them in a wrapper).")
    return np.stack(vectors)


class _Recorder:
    """The per-step reading of one env: the joint state ``[N, d_s]`` and the joint
    action ``[N, d_a]``; remembers each agent's last observation, so an agent that
    leaves the episode early keeps its last one."""

    def __init__(self, env: Any, use_state: bool | None) -> None:
        self.env = env
        self.agents = [str(a) for a in env.possible_agents]
        self.use_state = use_state
        self.last_obs: dict[str, np.ndarray] = {}

    def joint_state(self, observations: Mapping[str, Any]) -> np.ndarray:
        for a, o in observations.items():
            self.last_obs[str(a)] = _as_vector(o, f"agent {a!r}'s observation")
        if self.use_state is None:  # decided at the reset, kept for the episode
            try:
                self.env.state()
                self.use_state = True
            except (NotImplementedError, AttributeError):
                self.use_state = False
        if self.use_state:
            state = self.env.state()
            rows = agent_rows(state, len(self.agents))  # as JointAgentEnv reads it
            if rows is not None:
                return rows
            n = len(self.agents)
            raise ValueError(
                f"record_demonstrations: env.state() returned shape {np.shape(state)}, which is "
                f"neither [N, d_s] nor a flat [N * d_s] for N={n} agents; pass "
                f"use_state=False to record the stacked observations instead.")
        missing = [a for a in self.agents if a not in self.last_obs]
        if missing:
            raise ValueError(f"record_demonstrations: env.reset() gave no observation for "
                             f"{missing}; every possible agent must start in the episode.")
        return _stack([self.last_obs[a] for a in self.agents], "observations")


def record_demonstrations(
    env: Any, policy: Policy, n_episodes: int, seed: int, *,
    max_steps: int | None = None, use_state: bool | None = None,
) -> ContinuousDemonstrations:
    """Record ``n_episodes`` episodes of ``policy`` acting in the PettingZoo
    ``ParallelEnv`` ``env``: the way to turn a planner, a scripted controller or a
    trained policy into demonstrations.

    Each episode is reset with its own seed, drawn from ``np.random.default_rng(seed)``
    (stored in ``seeds``, so an episode can be replayed); the agents' action spaces are
    seeded from it too, so a policy that samples ``env.action_space(a)`` is
    reproducible. A policy with randomness of its own must carry its own seeded
    generator. A step:

    - the joint state is ``env.state()`` when the env implements it (``[N, d_s]``, or a
      flat ``[N * d_s]`` in ``env.possible_agents`` order, e.g. PettingZoo's MPE), else
      the agents' observations, each flattened, stacked in ``possible_agents`` order;
    - ``policy(observations, env)`` returns one action per live agent (``env.agents``);
      an agent that has left the episode keeps its last observation and records a zero
      action (``agent_lengths`` counts the steps each agent was live);
    - the episode ends when ``env.agents`` is empty (every agent terminated or
      truncated) or after ``max_steps`` steps.

    Args:
        env: a PettingZoo ``ParallelEnv`` (``reset(seed=)``, ``step``,
            ``possible_agents``, ``agents``; ``state()`` optional).
        policy: ``(observations dict, env) -> actions dict``.
        n_episodes: ``m``.
        seed: the only source of the episodes' seeds.
        max_steps: cut episodes longer than this (None: only the env ends them; an env
            that never does then loops forever).
        use_state: force ``env.state()`` (True) or the observations (False); None
            decides by whether ``env.state()`` is implemented.

    Returns:
        The episodes, padded to the longest, with ``agent_names = possible_agents``,
        their seeds and ``agent_lengths``.

    Raises:
        ValueError: bad arguments, a policy that does not act for exactly the live
            agents, an episode that ends before its first step, states / actions of
            different widths per agent, or an ``env.state()`` of another shape.
        TypeError: a policy that is not callable, non-numeric observations or actions.
    """
    if not is_int(n_episodes) or n_episodes < 1:
        raise ValueError(f"n_episodes must be a positive int, got {n_episodes!r}.")
    if not is_int(seed) or seed < 0:
        raise ValueError(f"seed must be a non-negative int, got {seed!r}; pass e.g. seed=0.")
    if max_steps is not None and (not is_int(max_steps) or max_steps < 1):
        raise ValueError(f"max_steps must be a positive int or None, got {max_steps!r}.")
    if not callable(policy):
        raise TypeError(f"policy must be callable as policy(observations, env) -> actions, "
                        f"got {type(policy).__name__}.")
    agents = [str(a) for a in env.possible_agents]
    seeds = np.random.default_rng(seed).integers(0, 2**31 - 1, size=n_episodes)
    episodes: list[tuple[np.ndarray, np.ndarray]] = []
    acted = np.zeros((n_episodes, len(agents)), dtype=np.int64)  # steps each agent was live
    for k, episode_seed in enumerate(seeds.tolist()):
        rec = _Recorder(env, use_state)
        observations, _ = env.reset(seed=episode_seed)
        for i, a in enumerate(env.possible_agents):
            space = env.action_space(a) if hasattr(env, "action_space") else None
            if hasattr(space, "seed"):
                space.seed(episode_seed + i)
        states, actions = [rec.joint_state(observations)], []
        while env.agents and (max_steps is None or len(actions) < max_steps):
            live = [str(a) for a in env.agents]
            # PettingZoo returns the observations of every agent that acted, those that
            # have just left included: the policy sees only the live ones.
            seen = {a: o for a, o in observations.items() if str(a) in live}
            chosen = policy(seen, env)
            if not isinstance(chosen, Mapping) or set(map(str, chosen)) != set(live):
                got = sorted(map(str, chosen)) if isinstance(chosen, Mapping) else chosen
                raise ValueError(
                    f"record_demonstrations: in episode {k}, step {len(actions)}, the "
                    f"policy returned {got!r}, but it must return a dict with one action "
                    f"for each live agent {live} (env.agents), no more, no fewer.")
            step = {str(a): _as_vector(v, f"agent {a!r}'s action") for a, v in chosen.items()}
            # Checked before the env sees the actions, so the message is ours, not the env's.
            d_a = _stack([step[a] for a in live], "actions").shape[1]
            if actions and d_a != actions[0].shape[1]:
                raise ValueError(f"record_demonstrations: in episode {k}, step {len(actions)}, "
                                 f"the actions have {d_a} components, but {actions[0].shape[1]} "
                                 f"at the episode's first step; keep the action width fixed.")
            # Agents that have left the episode record a zero action.
            actions.append(np.stack([step.get(a, np.zeros(d_a)) for a in agents]))
            acted[k] += [a in step for a in agents]
            observations, *_ = env.step(dict(chosen))
            states.append(rec.joint_state(observations))
        if not actions:
            raise ValueError(f"record_demonstrations: episode {k} (seed {episode_seed}) "
                             f"ended at its reset, before any step; nothing to record.")
        episodes.append((np.stack(states), np.stack(actions)))
    return _pad(episodes, agents, seeds, acted)


def _pad(episodes: Sequence[tuple[np.ndarray, np.ndarray]], agents: list[str],
         seeds: np.ndarray, acted: np.ndarray) -> ContinuousDemonstrations:
    shapes = {(s.shape[1:], a.shape[1:]) for s, a in episodes}
    if len(shapes) != 1:
        raise ValueError(f"record_demonstrations: the episodes' state and action shapes "
                         f"differ ({sorted(shapes)}); one set needs one [N, d_s] and "
                         f"[N, d_a].")
    S, A, lengths = pad_episodes(episodes)
    return ContinuousDemonstrations(states=S, actions=A, lengths=lengths,
                                    agent_names=tuple(agents), seeds=seeds.astype(np.int64),
                                    agent_lengths=acted)
