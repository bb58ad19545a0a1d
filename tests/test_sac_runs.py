"""The SAC-solved games (the drone arena, the MPE spread) through the one runner: a run
killed with SIGKILL and resumed, and a run with one process per learner, give the
uninterrupted all-in-one-process run's ``results.json`` (the SAC solvers' networks,
optimisers, replay buffers, environments and random streams are checkpointed exactly;
docs/design.md §8)."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
import torch
import torch.distributed as dist
from test_drone_dicrl import TINY
from test_mpe_task import CONFIG_TINY
from test_train_distributed import differences
from tiny_train import comparable, finished_run, train_cli

ROOT = Path(__file__).resolve().parents[1]
TRAIN = ROOT / "experiments" / "train.py"
# Two outer iterations: the crash after the first leaves one to resume.
# The drones' warm-up keeps the best of 3 lineages: with comm=distributed one per learner
# process and one in the process that trains C-ICRL beside them (table2's settings).
GAMES = {
    "drones": [*(o for o in TINY if not o.startswith("algo.outer_iterations=")),
               "solver.warmup_restarts=3", "solver.warmup_checks=2"],
    # one process, as the drones' here (mpe_quick ships learner processes)
    "mpe": ["experiment=mpe_quick", "comm=simulated",
            "solver.solver.demo_bc=0.5",  # its loss's state too
            *(o for o in CONFIG_TINY if not o.startswith("algo.outer_iterations="))],
}


def run(game: str, run_dir: Path, *extra: str, env: dict | None = None
        ) -> subprocess.CompletedProcess:
    # One thread in every process: the SAC networks compute in float32, and a matrix
    # product summed by another number of threads differs in the last bits (measured:
    # the learners' last-solve scores by ~1e-8 with 2 threads against 1 per process).
    # conftest.py sets that for this process and the ones a test starts.
    return train_cli(run_dir, *GAMES[game], "algo.outer_iterations=2", *extra, env=env)


@pytest.fixture(scope="module")
def game(request) -> str:
    return request.param


def games(default: str):
    """Both games, indirectly through the module's ``game`` fixture; only ``default`` in
    the default suite, the other marked slow: each property is checked there on one game,
    and both SAC games share the code under test."""
    return pytest.mark.parametrize(
        "game", [g if g == default else pytest.param(g, marks=pytest.mark.slow)
                 for g in sorted(GAMES)], indirect=True)


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory, game) -> Path:
    return finished_run(tmp_path_factory, game, run=lambda d, *e: run(game, d, *e))


def assert_same(run_dir: Path, reference: Path) -> None:
    got, want = comparable(run_dir), comparable(reference)
    for res in (got, want):  # how the learners were run, not what they computed
        res["config"].pop("comm")
    diffs = differences(got, want)
    assert not diffs, f"{len(diffs)} differences:\n" + "\n".join(diffs[:30])


@games(default="mpe")
def test_a_killed_run_resumes_to_the_uninterrupted_results(tmp_path, game, uninterrupted):
    crashed = run(game, tmp_path, env={"DICRL_CRASH_AFTER": "D-ICRL:1"})  # SIGKILL after it. 1
    assert crashed.returncode == -9, crashed.stderr[-3000:]
    saved = torch.load(tmp_path / "checkpoint.pt", weights_only=True)
    assert saved["D-ICRL"]["outer_iteration"] == 1
    assert len(saved["D-ICRL"]["learner_model"]["solvers"]) == 2  # both SAC solvers
    resumed = run(game, tmp_path, "resume=true")
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert "resuming from" in resumed.stdout
    # The warm-up is the crashed run's, loaded rather than trained again.
    assert "SAC warm-up loaded from" in resumed.stdout
    assert "SAC warm-up: " not in resumed.stdout
    assert_same(tmp_path, uninterrupted)


@pytest.mark.skipif(not (dist.is_available() and dist.is_gloo_available()),
                    reason="torch.distributed with gloo is not available")
@games(default="drones")  # C-ICRL beside the learner processes: table2's setting
def test_one_process_per_learner_gives_the_simulated_results(tmp_path, game, uninterrupted):
    out = run(game, tmp_path, "comm=distributed")
    assert out.returncode == 0, out.stderr[-3000:]
    assert "starting 2 learner processes" in out.stdout
    if game == "drones":  # C-ICRL beside the learners; each process trained one lineage
        assert "learner processes (1 thread(s) each), C-ICRL in this one" in out.stdout
        assert "waiting for lineages [1, 2] from the other learner processes" in out.stdout
    # C-ICRL, in this process, starts from the learners' warm-up file.
    assert "SAC warm-up loaded from" in out.stdout
    assert_same(tmp_path, uninterrupted)


@pytest.mark.slow  # two runs; the warm-up file's own checks: tests/test_mpe_task.py
@pytest.mark.parametrize("game", sorted(GAMES), indirect=True)
def test_a_warm_up_file_of_another_config_is_trained_again(tmp_path, game, uninterrupted):
    """A run directory reused under other settings: the old warm-up file is ignored and
    replaced, and the run is the uninterrupted one of its own config."""
    first = run(game, tmp_path, "seed=1")
    assert first.returncode == 0, first.stderr[-3000:]
    again = run(game, tmp_path)
    assert again.returncode == 0, again.stderr[-3000:]
    assert "SAC warm-up: " in again.stdout and "loaded from" not in again.stdout
    assert_same(tmp_path, uninterrupted)


@pytest.mark.skipif(not (dist.is_available() and dist.is_gloo_available()),
                    reason="torch.distributed with gloo is not available")
@pytest.mark.slow  # ~50 s; a dead learner is checked by tests/test_train_distributed.py
@pytest.mark.parametrize("game", ["drones"], indirect=True)
def test_a_dead_learner_stops_c_icrl_beside_it_and_resume_finishes_the_run(
        tmp_path, game, uninterrupted):
    """The drones' C-ICRL trains in the starting process beside the learner processes:
    learner 1 killed (SIGKILL) after its first outer iteration stops the whole run within
    a minute with its error and a resume hint, and resuming gives the uninterrupted
    results.json."""
    import time

    crashed = run("drones", tmp_path, "comm=distributed",
                  env={"DICRL_CRASH_AFTER": "D-ICRL@rank1:1"})
    elapsed = time.time() - (tmp_path / "checkpoint_rank1.pt").stat().st_mtime
    assert crashed.returncode == 1, crashed.stderr[-3000:]
    assert "rank 1: exited with code -9" in crashed.stderr
    assert f"resume=true hydra.run.dir={tmp_path}" in crashed.stderr
    assert elapsed < 60, f"the run ended {elapsed:.0f} s after learner 1 died"
    assert not (tmp_path / "results.json").exists()
    resumed = run("drones", tmp_path, "comm=distributed", "resume=true")
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert "SAC warm-up loaded from" in resumed.stdout
    assert_same(tmp_path, uninterrupted)
