"""A game of a user's own runs through ``experiments/train.py`` from its own config group
and task builder (tests/toy_game.py, tests/toy_configs/), with no change to the
library's runs/ or to experiments/: the environment's config names its builder
(``env.task._target_``), and nothing else in the entry point knows the game."""

from __future__ import annotations

import json
import os
from pathlib import Path

from pettingzoo.test import parallel_api_test
from tiny_train import train_cli
from toy_game import Crossing

HERE = Path(__file__).resolve().parent
SEARCH = f"hydra.searchpath=[file://{HERE / 'toy_configs'}]"


def test_the_toy_game_is_a_pettingzoo_parallel_env():
    parallel_api_test(Crossing(), num_cycles=20)


def test_a_game_of_ones_own_runs_end_to_end_through_the_entry_point(tmp_path):
    # A real command line: Hydra's search path is the user's way to add config groups.
    path = os.pathsep.join(filter(None, [str(HERE), os.environ.get("PYTHONPATH")]))
    out = train_cli(tmp_path, SEARCH, "experiment=toy", env={"PYTHONPATH": path})
    assert out.returncode == 0, out.stderr[-3000:]
    res = json.loads((tmp_path / "results.json").read_text())
    assert res["experiment"] == "toy"
    assert res["config"]["env"]["task"]["_target_"] == "toy_game.toy_task"
    rows = res["methods"]["D-ICRL"]["learners"]
    assert len(rows) == 2
    names = {f"agent{i}/cell({x},{y})" for i in range(2) for x in range(5) for y in range(5)}
    for row in rows:
        assert 0 <= row["SR"] <= 1 and 0 <= row["CVR"] <= 1
        assert set(row["constraints"]) <= names | {"proximity"}
    assert "D-ICRL 2" in out.stdout and str(tmp_path) in out.stdout
