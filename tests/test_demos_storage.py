"""Safe storage, validation and partitioning of demonstrations (dicrl_torch.demos)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from npz_files import rejects

from dicrl_torch.demos import (
    PAPER_SPLIT,
    Demonstrations,
    load_demonstrations,
    partition_demonstrations,
    save_demonstrations,
    validate_arrays,
)

N_CELLS, N_ACTIONS = 81, 9


def make_demos(m: int = 100, horizon: int = 5, n_experts: int = 3, seed: int = 0):
    rng = np.random.default_rng(seed)
    return Demonstrations(
        states=rng.integers(0, N_CELLS, size=(m, horizon + 1, n_experts)),
        actions=rng.integers(0, N_ACTIONS, size=(m, horizon, n_experts)),
        n_cells=N_CELLS,
        n_actions=N_ACTIONS,
    )


def valid_fields(m: int = 4, horizon: int = 3, n_experts: int = 2) -> dict:
    d = make_demos(m, horizon, n_experts)
    return {
        "states": np.array(d.states),
        "actions": np.array(d.actions),
        "n_cells": np.int64(N_CELLS),
        "n_actions": np.int64(N_ACTIONS),
        "format_version": np.int64(1),
    }


def write(path: Path, **overrides) -> Path:
    """An .npz with the valid fields, some replaced (value None drops the field)."""
    fields = valid_fields() | overrides
    np.savez(path, **{k: v for k, v in fields.items() if v is not None})
    return path


# ---- round trip ---------------------------------------------------------------------
def test_round_trip(tmp_path):
    demos = make_demos()
    path = save_demonstrations(tmp_path / "demos.npz", demos)
    loaded = load_demonstrations(path, n_cells=81, n_actions=9, n_experts=3, horizon=5)
    assert loaded == demos
    assert loaded.states.dtype == np.int64 and loaded.actions.dtype == np.int64
    assert (loaded.n_trajectories, loaded.horizon, loaded.n_experts) == (100, 5, 3)
    with np.load(path, allow_pickle=False) as z:
        assert sorted(z.files) == sorted(
            ["states", "actions", "n_cells", "n_actions", "format_version"]
        )
        assert z["format_version"].dtype == np.int64 and z["format_version"].ndim == 0


def test_save_is_atomic_and_leaves_no_temp_file(tmp_path):
    path = tmp_path / "sub" / "demos.npz"
    save_demonstrations(path, make_demos(seed=1))
    save_demonstrations(path, make_demos(seed=2))  # overwrite in place
    assert sorted(p.name for p in path.parent.iterdir()) == ["demos.npz"]
    assert load_demonstrations(path) == make_demos(seed=2)


def test_failed_save_leaves_no_temp_file(tmp_path):
    with pytest.raises(TypeError, match="Demonstrations"):
        save_demonstrations(tmp_path / "d.npz", {"states": 1})
    target = tmp_path / "dir_in_the_way"
    target.mkdir()  # os.replace onto a directory fails after the temp file is written
    with pytest.raises(OSError):
        save_demonstrations(target, make_demos())
    assert [p.name for p in tmp_path.iterdir()] == ["dir_in_the_way"]


def test_demonstrations_are_immutable_copies():
    states = np.zeros((2, 3, 1), dtype=np.int32)
    d = Demonstrations(states, np.zeros((2, 2, 1), dtype=np.int32), 4, 9)
    states[0, 0, 0] = 3
    assert d.states[0, 0, 0] == 0 and d.states.dtype == np.int64
    with pytest.raises(ValueError):
        d.states[0, 0, 0] = 1


def test_subset():
    d = make_demos(m=10)
    s = d.subset([3, 1])
    np.testing.assert_array_equal(s.states, d.states[[3, 1]])
    np.testing.assert_array_equal(s.actions, d.actions[[3, 1]])
    assert d.subset(np.arange(10) % 2 == 0).n_trajectories == 5
    with pytest.raises(ValueError, match="subset indices"):
        d.subset([10])
    with pytest.raises(ValueError, match="zero trajectories"):
        d.subset([])


def test_dataclass_validates():
    with pytest.raises(ValueError, match="Demonstrations.*'actions'"):
        Demonstrations(np.zeros((2, 3, 1), int), np.zeros((2, 3, 1), int), 4, 9)
    with pytest.raises(ValueError, match="'states'.*float"):
        validate_arrays(np.zeros((2, 3, 1)), np.zeros((2, 2, 1), int), 4, 9, source="x")


# ---- malformed files ----------------------------------------------------------------
def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.npz"):
        load_demonstrations(tmp_path / "nope.npz")


@pytest.mark.parametrize(
    ("overrides", "field", "extra"),
    [
        ({"states": np.zeros((4, 4), np.int64)}, "states", "shape"),
        ({"actions": np.zeros((4, 2, 2), np.int64)}, "actions", "shape"),
        ({"states": np.zeros((4, 4, 2), np.float64)}, "states", "integer"),
        ({"actions": np.full((4, 3, 2), np.nan)}, "actions", "NaN"),
        ({"states": np.full((4, 4, 2), np.inf)}, "states", "NaN or inf"),
        ({"states": np.full((4, 4, 2), N_CELLS, np.int64)}, "states",
         r"trajectory=0, time=0, expert=0"),
        ({"actions": np.full((4, 3, 2), -1, np.int64)}, "actions", "outside"),
        ({"states": np.zeros((0, 4, 2), np.int64), "actions": np.zeros((0, 3, 2), np.int64)},
         "states", "zero trajectories"),
        ({"states": None}, "states", "missing"),
        ({"extra": np.int64(1)}, "extra", "unknown"),
        ({"format_version": np.int64(2)}, "format_version", "version 1"),
        ({"n_cells": np.array([81])}, "n_cells", "scalar"),
    ],
)
def test_malformed_fields_rejected(tmp_path, overrides, field, extra):
    path = write(tmp_path / "bad.npz", **overrides)
    with pytest.raises(ValueError, match=rejects(path, field)) as info:
        load_demonstrations(path)
    assert re.search(extra, str(info.value)), str(info.value)


def test_out_of_range_reports_first_index(tmp_path):
    fields = valid_fields()
    fields["actions"][2, 1, 1] = N_ACTIONS
    path = write(tmp_path / "act.npz", **fields)
    with pytest.raises(ValueError, match=rejects(path, "actions")) as info:
        load_demonstrations(path)
    assert "trajectory=2, time=1, expert=1" in str(info.value)


def test_object_array_rejected_without_unpickling(tmp_path):
    path = write(tmp_path / "obj.npz", states=np.array([object()], dtype=object))
    with pytest.raises(ValueError, match=rejects(path, "states") + ".*pickled"):
        load_demonstrations(path)


def test_truncated_file(tmp_path):
    good = save_demonstrations(tmp_path / "good.npz", make_demos())
    path = tmp_path / "trunc.npz"
    data = good.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match=re.escape(path.name) + ".*corrupt"):
        load_demonstrations(path)


@pytest.mark.parametrize("content", [b"this is not a zip file at all", b""])
def test_garbage_file(tmp_path, content):
    path = tmp_path / "garbage.npz"
    path.write_bytes(content)
    with pytest.raises(ValueError, match=re.escape(path.name) + ".*npz"):
        load_demonstrations(path)


def test_plain_npy_rejected(tmp_path):
    path = tmp_path / "plain.npy"
    np.save(path, np.zeros(3, np.int64))
    with pytest.raises(ValueError, match=re.escape(path.name) + ".*not an .npz"):
        load_demonstrations(path)


@pytest.mark.parametrize(
    ("kwarg", "value"),
    [("n_experts", 3), ("horizon", 40), ("n_cells", 25), ("n_actions", 5)],
)
def test_mismatched_configuration(tmp_path, kwarg, value):
    path = write(tmp_path / "cfg.npz")  # 2 experts, horizon 3, 81 cells, 9 actions
    with pytest.raises(ValueError, match=rejects(path, kwarg) + ".*different configuration"):
        load_demonstrations(path, **{kwarg: value})


# ---- partition ----------------------------------------------------------------------
def test_paper_partition_is_disjoint_and_covering():
    demos = make_demos(m=100)
    shards = partition_demonstrations(demos, PAPER_SPLIT)
    assert [s.n_trajectories for s in shards] == [10, 20, 30, 40]
    np.testing.assert_array_equal(np.concatenate([s.states for s in shards]), demos.states)
    np.testing.assert_array_equal(np.concatenate([s.actions for s in shards]), demos.actions)


def test_shuffled_partition_is_deterministic_and_covering():
    # Distinct first states identify each trajectory.
    demos = make_demos(m=100)
    states = np.array(demos.states)
    states[:, 0, 0] = np.arange(100) % N_CELLS
    states[:, 0, 1] = np.arange(100) // N_CELLS
    demos = Demonstrations(states, demos.actions, N_CELLS, N_ACTIONS)

    def ids(shards):
        return [s.states[:, 0, 0] + N_CELLS * s.states[:, 0, 1] for s in shards]

    a = ids(partition_demonstrations(demos, PAPER_SPLIT, rng=np.random.default_rng(7)))
    b = ids(partition_demonstrations(demos, PAPER_SPLIT, rng=np.random.default_rng(7)))
    c = ids(partition_demonstrations(demos, PAPER_SPLIT, rng=np.random.default_rng(8)))
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    assert not all(np.array_equal(x, y) for x, y in zip(a, c, strict=True))
    assert sorted(np.concatenate(a).tolist()) == list(range(100))
    assert not np.array_equal(np.concatenate(a), np.arange(100))


@pytest.mark.parametrize(
    ("sizes", "match"),
    [((), "empty"), ((10, 20, 30), "sum to 60"), ((50, 0, 50), "positive"),
     ((110, -10), "positive"), ((50.0, 50), "positive")],
)
def test_bad_sizes_rejected(sizes, match):
    with pytest.raises(ValueError, match=match):
        partition_demonstrations(make_demos(m=100), sizes)


def test_bad_rng_rejected():
    with pytest.raises(TypeError, match="default_rng"):
        partition_demonstrations(make_demos(m=100), PAPER_SPLIT, rng=0)


# ---- property -----------------------------------------------------------------------
@st.composite
def demonstrations(draw):
    m, horizon, n = draw(st.integers(1, 6)), draw(st.integers(1, 6)), draw(st.integers(1, 3))
    n_cells, n_actions = draw(st.integers(1, 100)), draw(st.integers(1, 9))
    dtype = draw(st.sampled_from([np.int8, np.int16, np.int32, np.int64, np.uint8]))
    states = draw(hnp.arrays(dtype, (m, horizon + 1, n),
                             elements=st.integers(0, min(n_cells - 1, 127))))
    actions = draw(hnp.arrays(dtype, (m, horizon, n), elements=st.integers(0, n_actions - 1)))
    return Demonstrations(states, actions, n_cells, n_actions)


@settings(max_examples=50, deadline=None)
@given(demos=demonstrations())
def test_round_trip_property(tmp_path_factory, demos):
    path = tmp_path_factory.mktemp("prop") / "d.npz"
    save_demonstrations(path, demos)
    loaded = load_demonstrations(
        path, n_cells=demos.n_cells, n_actions=demos.n_actions,
        n_experts=demos.n_experts, horizon=demos.horizon,
    )
    assert loaded == demos
    np.testing.assert_array_equal(loaded.states, demos.states)
    np.testing.assert_array_equal(loaded.actions, demos.actions)
