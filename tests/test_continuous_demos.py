"""Continuous multi-agent demonstrations (issue 27): the validated ``.npz`` format and
the recorder for any PettingZoo ParallelEnv, on a tiny fake env defined here."""

from __future__ import annotations

import re

import numpy as np
import pytest
from gymnasium import spaces
from npz_files import assert_file_refused, assert_not_an_archive
from pettingzoo import ParallelEnv

from dicrl_torch.demos import Trajectories, partition_demonstrations
from dicrl_torch.demos.continuous import (
    FORMAT_VERSION,
    ContinuousDemonstrations,
    load_continuous_demonstrations,
    record_demonstrations,
    save_continuous_demonstrations,
)

DT = 0.1


class PointsEnv(ParallelEnv):
    """``n`` points in the plane moved by velocity commands: ``x <- x + DT * a``. Agent
    ``i`` leaves the episode after ``3 + i`` steps (its point then stays put); all are
    truncated after ``limit`` steps. Observations are ``(x, y, t)``; ``state()`` is the
    positions ``[n, 2]`` (``state="joint"``), flat ``[2 n]`` (``"flat"``) or PettingZoo's
    default, not implemented (``None``)."""

    metadata = {"name": "points_v0"}

    def __init__(self, n: int = 3, limit: int = 10, state: str | None = "joint") -> None:
        self.possible_agents = [f"p{i}" for i in range(n)]
        self.agents: list[str] = []
        self.limit, self.kind = limit, state
        self._spaces = {a: spaces.Box(-1.0, 1.0, (2,), np.float64) for a in self.possible_agents}

    def action_space(self, agent):
        return self._spaces[agent]

    def observation_space(self, agent):
        return spaces.Box(-np.inf, np.inf, (3,), np.float64)

    def reset(self, seed=None, options=None):
        rng = np.random.default_rng(seed)
        self.pos = rng.uniform(-1, 1, (len(self.possible_agents), 2))
        self.t = 0
        self.agents = list(self.possible_agents)
        return self._obs(self.agents), {a: {} for a in self.agents}

    def _obs(self, agents):
        return {a: np.array([*self.pos[self._i(a)], self.t], dtype=np.float64) for a in agents}

    def _i(self, agent):
        return self.possible_agents.index(agent)

    def step(self, actions):
        assert set(actions) == set(self.agents)
        for a, u in actions.items():
            self.pos[self._i(a)] += DT * np.asarray(u)
        self.t += 1
        acted = list(self.agents)
        term = {a: self.t >= 3 + self._i(a) for a in acted}
        trunc = {a: self.t >= self.limit for a in acted}
        self.agents = [a for a in acted if not (term[a] or trunc[a])]
        return self._obs(acted), {a: 0.0 for a in acted}, term, trunc, {a: {} for a in acted}

    def state(self):
        if self.kind is None:
            return super().state()  # PettingZoo's NotImplementedError
        return self.pos.copy() if self.kind == "joint" else self.pos.reshape(-1).copy()


def towards_origin(observations, env):
    return {a: -0.5 * o[:2] for a, o in observations.items()}


def random_actions(observations, env):
    return {a: env.action_space(a).sample() for a in observations}


def arrays(m=4, T=6, N=3, d_s=2, d_a=2, seed=0):
    rng = np.random.default_rng(seed)
    lengths = rng.integers(1, T + 1, size=m)
    lengths[0] = T
    return rng.normal(size=(m, T + 1, N, d_s)), rng.normal(size=(m, T, N, d_a)), lengths


# ================================================================ in memory, padding
def test_padding_is_canonical_ignored_and_nan_free():
    S, A, L = arrays()
    L[1] = 2
    S[1, 3:] = np.nan  # past the end of episode 1: padding
    A[1, 2:] = np.inf
    d = ContinuousDemonstrations(S, A, L)
    assert np.isfinite(d.states).all() and np.isfinite(d.actions).all()
    assert (d.states[1, 3:] == d.states[1, 2]).all() and (d.actions[1, 2:] == 0).all()
    assert np.array_equal(d.states[1, :3], S[1, :3]) and np.array_equal(d.actions[1, :2],
                                                                         A[1, :2])
    # Two sets differing only in their padding are equal.
    S2, A2 = S.copy(), A.copy()
    S2[1, 3:], A2[1, 2:] = 7.0, -3.0
    assert ContinuousDemonstrations(S2, A2, L) == d
    s, a = d.episode(1)
    assert s.shape == (3, 3, 2) and a.shape == (2, 3, 2)
    assert d.step_mask()[1].tolist() == [True, True, False, False, False, False]
    assert d.state_mask()[1].sum() == 3
    assert (d.n_episodes, d.horizon, d.n_agents, d.state_dim, d.action_dim) == (4, 6, 3, 2, 2)
    with pytest.raises(ValueError, match="read-only"):
        d.states[0, 0, 0, 0] = 1.0
    assert S[1, 3, 0, 0] != S[1, 3, 0, 0]  # the caller's array is untouched (still NaN)


def test_subsets_partition_and_equality():
    S, A, L = arrays(m=5)
    d = ContinuousDemonstrations(S, A, L, agent_names=("a", "b", "c"), seeds=np.arange(5))
    assert isinstance(d, Trajectories)
    sub = d.subset([3, 1])
    assert sub.n_episodes == 2 and sub.seeds.tolist() == [3, 1]
    assert np.array_equal(sub.states[0], d.states[3]) and sub.agent_names == ("a", "b", "c")
    shards = partition_demonstrations(d, (2, 3))
    assert [s.n_episodes for s in shards] == [2, 3]
    assert d != ContinuousDemonstrations(S, A, L, seeds=np.arange(5))
    assert d != d.subset([0, 1, 2, 3, 4][::-1])


BAD = {
    # name: (mutate(states, actions, lengths, kw) -> tuple, message regex)
    "int-states": (lambda S, A, L, kw: (S.astype(np.int64), A, L, kw),
                   r"'states' has dtype int64.*astype\(np.float64\)"),
    "3d-states": (lambda S, A, L, kw: (S[..., 0], A, L, kw), r"'states' must have 4 dims"),
    "3d-actions": (lambda S, A, L, kw: (S, A[..., 0], L, kw), r"'actions' must have 4 dims"),
    "m": (lambda S, A, L, kw: (S, A[:-1], L, kw), r"'actions'.*3 episodes m.*has 4"),
    "T": (lambda S, A, L, kw: (S, A[:, :-1], L, kw), r"'actions'.*5 steps T.*has 6"),
    "N": (lambda S, A, L, kw: (S, A[:, :, :2], L, kw), r"'actions'.*2 agents N.*has 3"),
    "d_a=0": (lambda S, A, L, kw: (S, A[..., :0], L, kw), r"'actions'.*d_a = 0"),
    "no-steps": (lambda S, A, L, kw: (S[:, :1], A[:, :0], L, kw), r"T\+1 >= 2"),
    "float-lengths": (lambda S, A, L, kw: (S, A, L * 1.0, kw), r"'lengths' must be an integ"),
    "lengths-shape": (lambda S, A, L, kw: (S, A, L[:2], kw), r"'lengths'.*shape \(4,\)"),
    "length-0": (lambda S, A, L, kw: (S, A, np.r_[L[:3], 0], kw),
                 r"'lengths' holds 0 for episode 3, outside \[1, T=6\]"),
    "length-long": (lambda S, A, L, kw: (S, A, np.r_[7, L[1:]], kw),
                    r"'lengths' holds 7 for episode 0, outside \[1, T=6\]"),
    "nan-state": (lambda S, A, L, kw: (_set(S, (0, 6, 2, 1), np.nan), A, L, kw),
                  r"'states' holds nan at \(episode=0, time=6, agent=2, component=1\)"
                  r".*lengths\[0\] = 6"),
    "inf-action": (lambda S, A, L, kw: (S, _set(A, (0, 5, 1, 0), np.inf), L, kw),
                   r"'actions' holds inf at \(episode=0, time=5, agent=1, component=0\)"),
    "names-count": (lambda S, A, L, kw: (S, A, L, {"agent_names": ("a", "b")}),
                    r"'agent_names' must be 3 strings"),
    "names-dupe": (lambda S, A, L, kw: (S, A, L, {"agent_names": ("a", "b", "a")}),
                   r"'agent_names'.*repeated \['a'\]"),
    "names-empty": (lambda S, A, L, kw: (S, A, L, {"agent_names": ("a", "", "c")}),
                    r"'agent_names'.*empty at \[1\]"),
    "seeds": (lambda S, A, L, kw: (S, A, L, {"seeds": np.array([0, 1, -1, 2])}),
              r"'seeds' must be non-negative ints of shape \(4,\)"),
}


def _set(a, idx, value):
    a = a.copy()
    a[idx] = value
    return a


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_arrays_are_refused_with_field_and_fix(case):
    mutate, message = BAD[case]
    S, A, L, kw = mutate(*arrays(), {})
    with pytest.raises(ValueError, match="ContinuousDemonstrations: .*" + message):
        ContinuousDemonstrations(S, A, L, **kw)


# ====================================================================== on disk
def test_round_trip_and_expected_dims(tmp_path):
    S, A, L = arrays()
    S[2, L[2] + 1:] = np.nan
    d = ContinuousDemonstrations(S, A, L, agent_names=("u", "v", "w"), seeds=[4, 3, 2, 1])
    path = save_continuous_demonstrations(tmp_path / "sub" / "demos.npz", d)
    assert path == tmp_path / "sub" / "demos.npz"  # no suffix added, parents created
    back = load_continuous_demonstrations(path, n_agents=3, state_dim=2, action_dim=2,
                                          horizon=6)
    assert back == d and back.agent_names == ("u", "v", "w")
    with np.load(path, allow_pickle=False) as f:  # names stored as a unicode array
        assert f["agent_names"].dtype.kind == "U" and int(f["format_version"]) == 1
    bare = ContinuousDemonstrations(S, A, L)
    assert load_continuous_demonstrations(
        save_continuous_demonstrations(tmp_path / "bare.npz", bare)) == bare
    for name, value in (("n_agents", 2), ("state_dim", 4), ("action_dim", 1), ("horizon", 9)):
        with pytest.raises(ValueError, match=re.escape("demos.npz") + f".*'{name}' is .* but "
                           f"{value} was expected.*Regenerate"):
            load_continuous_demonstrations(path, **{name: value})
    with pytest.raises(FileNotFoundError, match="record_demonstrations"):
        load_continuous_demonstrations(tmp_path / "missing.npz")
    with pytest.raises(TypeError, match="expects a ContinuousDemonstrations"):
        save_continuous_demonstrations(tmp_path / "x.npz", (S, A, L))


def _fields() -> dict:
    S, A, L = arrays()
    return {"states": S, "actions": A, "lengths": L, "format_version": np.int64(FORMAT_VERSION)}


BAD_FILES = {
    "missing": ("lengths", lambda f: f.pop("lengths")),
    "missing-version": ("format_version", lambda f: f.pop("format_version")),
    "unknown": ("extra", lambda f: f.update(extra=np.zeros(2))),
    "version": ("format_version", lambda f: f.update(format_version=np.int64(99))),
    "object": ("actions", lambda f: f.update(actions=f["actions"].astype(object))),
    "ndim": ("states", lambda f: f.update(states=f["states"][..., 0])),
    "T": ("actions", lambda f: f.update(actions=f["actions"][:, 1:])),
    "N": ("actions", lambda f: f.update(actions=f["actions"][:, :, 1:])),
    "nan": ("states", lambda f: f["states"].__setitem__((0, 0, 0, 0), np.nan)),
    "lengths": ("lengths", lambda f: f["lengths"].__setitem__(1, 0)),
    "names": ("agent_names", lambda f: f.update(agent_names=np.array(["a", "b"]))),
    "int-names": ("agent_names", lambda f: f.update(agent_names=np.arange(3))),
}


@pytest.mark.parametrize("case", sorted(BAD_FILES))
def test_malformed_files_are_refused_naming_file_and_field(tmp_path, case):
    field, mutate = BAD_FILES[case]
    f = _fields()
    mutate(f)
    assert_file_refused(load_continuous_demonstrations, tmp_path / f"bad_{case}.npz", f, field)


def test_nan_in_padding_loads(tmp_path):
    f = _fields()
    f["lengths"][1] = 2
    f["states"][1, 3:] = np.nan
    np.savez(tmp_path / "padded.npz", **f)
    d = load_continuous_demonstrations(tmp_path / "padded.npz")
    assert np.isfinite(d.states).all() and d.lengths[1] == 2


def test_not_an_archive(tmp_path):
    assert_not_an_archive(load_continuous_demonstrations, tmp_path)


def test_agent_lengths_mask_the_actions_of_agents_that_left(tmp_path):
    """``agent_lengths [m, N]``: the steps each agent acted. The recorder counts them;
    they round-trip through the file; "everyone acted throughout" is stored as None, so
    both ways of saying it are equal; out-of-range entries are refused by field."""
    d = record_demonstrations(PointsEnv(n=3, limit=10), towards_origin, 2, seed=3)
    assert d.agent_lengths.tolist() == [[3, 4, 5]] * 2  # agent i leaves after 3 + i steps
    mask = d.acting_mask()
    assert mask.shape == (2, 5, 3) and mask.sum(1).tolist() == [[3, 4, 5]] * 2
    path = save_continuous_demonstrations(tmp_path / "acted.npz", d)
    assert load_continuous_demonstrations(path) == d
    plain = ContinuousDemonstrations(states=d.states, actions=d.actions, lengths=d.lengths)
    full = ContinuousDemonstrations(states=d.states, actions=d.actions, lengths=d.lengths,
                                    agent_lengths=np.full((2, 3), 5))
    assert full.agent_lengths is None and full == plain
    assert plain.acting_mask().all() and plain != d
    with pytest.raises(ValueError, match=r"field 'agent_lengths' holds 6 for episode 0, "
                                         r"agent 1.*lengths\[0\] = 5"):
        ContinuousDemonstrations(states=d.states, actions=d.actions, lengths=d.lengths,
                                 agent_lengths=np.array([[5, 6, 5], [5, 5, 5]]))
    with pytest.raises(ValueError, match=r"field 'agent_lengths' must be ints of shape \(2, 3\)"):
        ContinuousDemonstrations(states=d.states, actions=d.actions, lengths=d.lengths,
                                 agent_lengths=np.ones((2, 2), np.int64))


# ====================================================================== recorder
def test_record_uses_state_and_matches_the_dynamics():
    env = PointsEnv(n=3, limit=10)
    d = record_demonstrations(env, towards_origin, n_episodes=3, seed=7)
    # Agent i leaves after 3 + i steps, so every episode takes 5 steps.
    assert d.states.shape == (3, 6, 3, 2) and d.actions.shape == (3, 5, 3, 2)
    assert d.lengths.tolist() == [5, 5, 5] and d.agent_names == ("p0", "p1", "p2")
    assert d.seeds.tolist() == np.random.default_rng(7).integers(0, 2**31 - 1, 3).tolist()
    for k in range(3):
        # The first state is the reset's, from the episode's seed.
        start = np.random.default_rng(int(d.seeds[k])).uniform(-1, 1, (3, 2))
        assert np.array_equal(d.states[k, 0], start)
        for t in range(5):
            for i in range(3):
                live = t < 3 + i
                want = -0.5 * d.states[k, t, i] if live else np.zeros(2)
                assert np.allclose(d.actions[k, t, i], want)
                assert np.allclose(d.states[k, t + 1, i], d.states[k, t, i] + DT * want)


def test_record_falls_back_to_observations_and_flat_state():
    obs = record_demonstrations(PointsEnv(state=None), towards_origin, 2, seed=1)
    assert obs.state_dim == 3  # (x, y, t): the stacked observations
    # An agent that has left keeps its last observation: p0 left at t = 3.
    assert (obs.states[:, 3:, 0] == obs.states[:, 3:4, 0]).all()
    assert obs.states[0, 2, 1, 2] == 2.0 and obs.states[0, 5, 2, 2] == 5.0
    forced = record_demonstrations(PointsEnv(state="joint"), towards_origin, 2, seed=1,
                                   use_state=False)
    assert forced == obs
    flat = record_demonstrations(PointsEnv(state="flat"), towards_origin, 2, seed=1)
    joint = record_demonstrations(PointsEnv(state="joint"), towards_origin, 2, seed=1)
    assert flat == joint and np.allclose(flat.states[..., :2], obs.states[..., :2])


def test_record_is_seeded_cut_by_max_steps_and_saves(tmp_path):
    a = record_demonstrations(PointsEnv(), random_actions, 3, seed=5)
    assert a == record_demonstrations(PointsEnv(), random_actions, 3, seed=5)
    assert a != record_demonstrations(PointsEnv(), random_actions, 3, seed=6)
    cut = record_demonstrations(PointsEnv(), random_actions, 3, seed=5, max_steps=2)
    assert cut.lengths.tolist() == [2, 2, 2]
    assert np.array_equal(cut.states, a.states[:, :3])
    short = record_demonstrations(PointsEnv(n=3, limit=4), random_actions, 2, seed=0)
    assert short.lengths.tolist() == [4, 4]  # truncated by the env
    path = save_continuous_demonstrations(tmp_path / "rec.npz", a)
    assert load_continuous_demonstrations(path, n_agents=3, state_dim=2, action_dim=2) == a


def test_record_refuses_bad_policies_and_arguments():
    env = PointsEnv()

    def skips_one(observations, env):
        return {a: np.zeros(2) for a in list(observations)[1:]}

    with pytest.raises(ValueError, match=r"episode 0, step 0.*each live agent \['p0', 'p1'"):
        record_demonstrations(env, skips_one, 1, seed=0)
    with pytest.raises(ValueError, match="dict with one action"):
        record_demonstrations(env, lambda o, e: [0.0, 0.0], 1, seed=0)

    def ragged(observations, env):
        return {a: np.zeros(1 + i) for i, a in enumerate(observations)}

    with pytest.raises(ValueError, match="actions have different sizes"):
        record_demonstrations(env, ragged, 1, seed=0)
    with pytest.raises(ValueError, match="n_episodes must be a positive int"):
        record_demonstrations(env, towards_origin, 0, seed=0)
    with pytest.raises(ValueError, match="seed must be a non-negative int"):
        record_demonstrations(env, towards_origin, 1, seed=None)
    with pytest.raises(ValueError, match="max_steps"):
        record_demonstrations(env, towards_origin, 1, seed=0, max_steps=0)
    with pytest.raises(TypeError, match="policy must be callable"):
        record_demonstrations(env, "planner", 1, seed=0)
    bad_state = PointsEnv()
    bad_state.state = lambda: np.zeros(7)
    with pytest.raises(ValueError, match=r"env.state\(\) returned shape \(7,\).*use_state"):
        record_demonstrations(bad_state, towards_origin, 1, seed=0)
