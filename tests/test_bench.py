"""``python -m dicrl_torch.bench sac``: its settings are table2_quick's, and it prints the
JSON line the interface promises (docs/design.md §8)."""

from __future__ import annotations

import inspect
import json

from hydra import compose, initialize_config_dir

from dicrl_torch import bench
from dicrl_torch.solvers.sac import SACConstrainedSolver
from tests.tiny_train import CONFIGS


def test_the_sac_bench_runs_table2_quicks_solver_settings():
    with initialize_config_dir(config_dir=str(CONFIGS), version_base=None):
        cfg = compose("train", overrides=["experiment=table2_quick"])
    solver = cfg.solver.solver
    defaults = {k: p.default for k, p in
                inspect.signature(SACConstrainedSolver).parameters.items()}
    for key, value in bench.TABLE2_QUICK_SOLVER.items():
        want = list(value) if isinstance(value, tuple) else value
        assert solver.get(key, defaults[key]) == want, key
    dynamics = cfg.env.arena.dynamics
    for key, value in bench.TABLE2_QUICK_DYNAMICS.items():
        assert dynamics[key] == value, key


def test_the_sac_bench_prints_both_loops_and_their_ratio(capsys):
    assert bench.main(["sac", "--steps", "8", "--repeat", "1"]) == 0
    line = json.loads(capsys.readouterr().out.strip())
    for loop in ("sb3", "lean"):
        assert line["loops"][loop]["updates_per_s"] > 0
        assert line["loops"][loop]["env_steps_per_s"] > 0
    ratio = line["ratio"]["updates_per_s"]
    assert ratio == line["loops"]["lean"]["updates_per_s"] / line["loops"]["sb3"]["updates_per_s"]


def test_the_certificate_bench_times_both_paths_on_the_same_candidates(capsys):
    assert bench.main(["certificate", "--experts", "2", "--candidates", "2",
                       "--demonstrations", "20", "--horizon", "12"]) == 0
    line = json.loads(capsys.readouterr().out.strip())
    assert line["candidates"] == 2 and line["same_probabilities"] is True
    assert all(0 < k < line["cells"] for k in line["open_cells"])
    assert line["ratio"]["solve"] == line["full_solve_s"] / line["open_solve_s"]
