"""experiments/train.py with one process per learner (``comm=distributed``), spawned by
the entry point or started by torchrun: the same results.json as the all-in-one-process
simulated run, bit for bit; a dead learner fails the run and resume finishes it."""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
import tiny_train
import torch
import torch.distributed as dist

from dicrl_torch.runs.runner import TRAFFIC_KEYS

ROOT = Path(__file__).resolve().parents[1]
TORCHRUN = Path(sys.executable).parent / "torchrun"
# the shared tiny job (tests/tiny_train.py) with 2 outer iterations
TINY = ["algo.outer_iterations=2" if o.startswith("algo.outer_iterations=") else o
        for o in tiny_train.TINY]
# Bit-for-bit equality holds at equal threads per learner: a reduction split over 2
# threads (the simulated run's default on 2 cores) rounds differently from 1 thread (a
# spawned learner's share), seen as a 1-ulp difference in lga_norm on this machine.
ONE_THREAD = {**os.environ, "DICRL_THREADS": "1"}

pytestmark = pytest.mark.skipif(not (dist.is_available() and dist.is_gloo_available()),
                                reason="torch.distributed with gloo is not available")


def run_train(run_dir, *extra, env=None, launcher=(sys.executable,)):
    return subprocess.run(
        [*launcher, str(tiny_train.TRAIN), f"hydra.run.dir={run_dir}",
         *TINY, *extra], capture_output=True, text=True, cwd=ROOT, timeout=300,
        env={**ONE_THREAD, **(env or {})})


def torchrun(n: int) -> tuple[str, ...]:
    if not TORCHRUN.exists():
        pytest.skip(f"no torchrun next to {sys.executable}")
    return (str(TORCHRUN), "--standalone", "--nproc_per_node", str(n))


def differences(a, b, where="") -> list[str]:
    """Every place where ``a`` and ``b`` differ, with |difference| for numbers. The
    learners' control traffic is left out: learner processes agree on the run directory
    and the checkpoints to resume from, which one process holding every learner need not;
    every other phase of the traffic (the algorithm's rounds, the diagnostics) must match."""
    if where.endswith((".traffic.sent.control", ".traffic.received.control")):
        return []
    if isinstance(a, dict) and isinstance(b, dict):
        if a.keys() != b.keys():
            return [f"{where}: keys {sorted(a)} != {sorted(b)}"]
        return [d for k in a for d in differences(a[k], b[k], f"{where}.{k}")]
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        return [d for i, (x, y) in enumerate(zip(a, b, strict=True))
                for d in differences(x, y, f"{where}[{i}]")]
    if isinstance(a, float) and isinstance(b, float) and not (math.isnan(a) and math.isnan(b)):
        return [] if a == b else [f"{where}: {a!r} vs {b!r} (|diff| {abs(a - b):.3g})"]
    return [] if a == b else [f"{where}: {a!r} vs {b!r}"]


def assert_same_results(run_dir: Path, reference: Path) -> None:
    """D-ICRL, C-ICRL and expert rows, histories and disagreement: exactly equal."""
    got, want = (json.loads((p / "results.json").read_text()) for p in (run_dir, reference))
    assert len(got["methods"]["D-ICRL"]["learners"]) == 2
    diffs = differences({k: got[k] for k in ("methods", "history",
                                             "consensus_max_pairwise_cost_distance")},
                        {k: want[k] for k in ("methods", "history",
                                              "consensus_max_pairwise_cost_distance")})
    assert not diffs, f"{len(diffs)} differences:\n" + "\n".join(diffs[:30])


def assert_unclassified(got: dict, want: dict) -> None:
    """No process of a run on private shard files holds every demonstration, so the
    identifiability of the true set and the region scores that set undetermined states
    apart (evaluations on the pooled data) are not computed: their fields are null in
    ``got``; they are dropped from both for the comparison."""
    from dicrl_torch.runs.grid import ANNOTATIONS
    from dicrl_torch.runs.grid_regions import POOLED_SCORES

    assert got.get("identifiability") is None and want["identifiability"] is not None
    for res, computed in ((got, False), (want, True)):
        for row in res["methods"]["D-ICRL"]["learners"]:
            assert (row["FNR_required"] is not None) == computed
            for key in POOLED_SCORES:
                assert (row.pop(key) is not None) == computed, key
            for key in ANNOTATIONS:
                row.pop(key)


@pytest.fixture(scope="module")
def simulated(tmp_path_factory) -> Path:
    """The reference: every learner in one process (comm=simulated, the default), this
    one (one torch thread, as each learner process has)."""
    return tiny_train.finished_run(
        tmp_path_factory, "simulated",
        run=lambda run_dir, *extra: tiny_train.train_here(run_dir, *TINY, *extra))


@pytest.fixture(scope="module")
def spawned(tmp_path_factory) -> Path:
    run_dir = tmp_path_factory.mktemp("spawned")
    out = run_train(run_dir, "comm=distributed")
    assert out.returncode == 0, out.stderr[-3000:]
    assert "starting 2 learner processes" in out.stdout and "D-ICRL 2" in out.stdout
    return run_dir


def test_spawned_learners_reproduce_the_simulated_run(spawned, simulated):
    assert_same_results(spawned, simulated)
    for r in (0, 1):
        part = json.loads((spawned / "learner_rows" / f"rank{r}.json").read_text())
        assert part["rank"] == r and part["world_size"] == 2
        saved = torch.load(spawned / f"checkpoint_rank{r}.pt", weights_only=True)
        assert saved["D-ICRL"]["outer_iteration"] == 2
        assert saved["D-ICRL:previous"]["outer_iteration"] == 1
        # each learner's own row, as it wrote it for rank 0 to merge (with its traffic)
        assert saved["D-ICRL:evaluated"]["rows"] == [
            {k: v for k, v in part["row"].items() if k not in TRAFFIC_KEYS}]
        assert part["row"]["traffic"]["algorithm_bytes_sent"] > 0
    assert set(torch.load(spawned / "checkpoint.pt", weights_only=True)) == {
        "C-ICRL", "C-ICRL:evaluated"}
    cfg = json.loads((spawned / "results.json").read_text())["config"]["comm"]
    assert cfg["_target_"].endswith("DistributedCommunicator") and cfg["backend"] == "gloo"


def test_torchrun_learners_reproduce_the_simulated_run(tmp_path, simulated):
    out = run_train(tmp_path, "comm=distributed", launcher=torchrun(2))
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.count("D-ICRL 2") == 1  # only rank 0 prints the table
    assert_same_results(tmp_path, simulated)


@pytest.mark.slow  # ~15 s: a torchrun start-up to reach one check of the split
def test_torchrun_world_size_must_match_the_split(tmp_path):
    out = run_train(tmp_path, "comm=distributed", launcher=torchrun(3))
    assert out.returncode != 0
    assert ("torchrun started WORLD_SIZE=3 processes but split=[4, 6] has 2 learners"
            in out.stderr)
    assert "--nproc_per_node 2" in out.stderr
    assert not (tmp_path / "results.json").exists()


def test_a_dead_learner_fails_the_run_and_resume_finishes_it(tmp_path, simulated):
    crashed = run_train(tmp_path, "comm=distributed",
                        env={"DICRL_CRASH_AFTER": "D-ICRL@rank1:1"})  # SIGKILL after it. 1
    # From learner 1's death (its last checkpoint is written right before it) to the end
    # of the run: start-up is left out, which on a loaded machine alone can take a minute.
    elapsed = time.time() - (tmp_path / "checkpoint_rank1.pt").stat().st_mtime
    assert crashed.returncode == 1, crashed.stderr[-3000:]
    err = crashed.stderr
    assert "rank 1: exited with code -9" in err
    assert "rank 0: PeerFailureError: Learner 0 of 2" in err  # no waiting for the dead peer
    assert f"resume=true hydra.run.dir={tmp_path}" in err
    assert elapsed < 60, f"the run ended {elapsed:.0f} s after learner 1 died"
    assert not (tmp_path / "results.json").exists()
    for r in (0, 1):
        saved = torch.load(tmp_path / f"checkpoint_rank{r}.pt", weights_only=True)
        assert saved["D-ICRL"]["outer_iteration"] == 1
    resumed = run_train(tmp_path, "comm=distributed", "resume=true")
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert "D-ICRL learners continue after outer iteration 1" in resumed.stdout
    assert_same_results(tmp_path, simulated)


@pytest.mark.slow  # ~10 s
def test_resume_when_one_learner_is_a_save_behind(tmp_path, spawned, simulated):
    """Learner 1 died after the last exchange of iteration 2 but before saving it:
    learner 0 falls back to its previous save, and the run ends as if never stopped."""
    run_dir = tmp_path / "run"
    shutil.copytree(spawned, run_dir)
    (run_dir / "results.json").unlink()
    path = run_dir / "checkpoint_rank1.pt"
    saved = torch.load(path, weights_only=True)
    torch.save({"D-ICRL": saved["D-ICRL:previous"]}, path)
    resumed = run_train(run_dir, "comm=distributed", "resume=true")
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert "D-ICRL learners continue after outer iteration 1" in resumed.stdout
    assert_same_results(run_dir, simulated)


@pytest.mark.slow  # ~10 s
def test_a_dead_learner_fails_a_torchrun_run(tmp_path):
    t0 = time.monotonic()
    out = run_train(tmp_path, "comm=distributed", launcher=torchrun(2),
                    env={"DICRL_CRASH_AFTER": "D-ICRL@rank1:1"})
    assert out.returncode != 0
    assert time.monotonic() - t0 < 60
    assert "exitcode  : -9" in out.stderr  # torchrun's report on rank 1
    assert not (tmp_path / "results.json").exists()
    for r in (0, 1):
        assert (tmp_path / f"checkpoint_rank{r}.pt").exists()


@pytest.mark.slow  # ~35 s; SIGTERM of a one-process run: tests/test_robustness.py
def test_sigterm_stops_a_torchrun_run_and_resume_finishes_it(tmp_path, simulated):
    """A learner that receives SIGTERM stops at once with a message and the resume
    command; the others fail fast; resuming under torchrun gives the uninterrupted run."""
    t0 = time.monotonic()
    stopped = run_train(tmp_path, "comm=distributed", launcher=torchrun(2),
                        env={"DICRL_CRASH_AFTER": "D-ICRL@rank1:1",
                             "DICRL_CRASH_SIGNAL": "TERM"})
    assert stopped.returncode != 0
    assert time.monotonic() - t0 < 60
    assert "error: learner 1: interrupted by SIGTERM" in stopped.stderr
    # Learner 0 notices the dead peer in its next exchange, or, when it is computing
    # between exchanges as learner 1 exits, torchrun stops it first: a race either way
    # settled within seconds (the bound above), never a wait for the timeout.
    assert ("error: learner 0: PeerFailureError" in stopped.stderr
            or "error: learner 0: interrupted by SIGTERM" in stopped.stderr), stopped.stderr[-3000:]
    assert f"resume=true hydra.run.dir={tmp_path}" in stopped.stderr
    assert not (tmp_path / "results.json").exists()
    resumed = run_train(tmp_path, "comm=distributed", "resume=true", launcher=torchrun(2))
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert_same_results(tmp_path, simulated)


@pytest.mark.slow  # ~18 s; own shard files: tests/test_configs.py, in process
def test_torchrun_learners_on_their_own_shard_files(tmp_path, simulated):
    """Each torchrun learner reads only its own file (rank 0 pools nothing without C-ICRL):
    the D-ICRL rows and history equal those of the simulated run that drew the data."""
    from dicrl_torch.demos import (
        load_demonstrations,
        partition_demonstrations,
        save_demonstrations,
    )

    demos = load_demonstrations(simulated / "demos.npz")
    files = [str(save_demonstrations(tmp_path / f"learner{v}.npz", shard))
             for v, shard in enumerate(partition_demonstrations(demos, [4, 6]))]
    run_dir = tmp_path / "run"
    out = run_train(run_dir, "comm=distributed", "algo.run_c_icrl=false",
                    f"shard_files=[{','.join(files)}]", launcher=torchrun(2))
    assert out.returncode == 0, out.stderr[-3000:]
    got, want = (json.loads((p / "results.json").read_text()) for p in (run_dir, simulated))
    assert "C-ICRL" not in got["methods"] and not (run_dir / "demos.npz").exists()
    assert_unclassified(got, want)
    diffs = differences(
        [got["methods"]["D-ICRL"], got["history"]["D-ICRL"],
         got["consensus_max_pairwise_cost_distance"]],
        [want["methods"]["D-ICRL"], want["history"]["D-ICRL"],
         want["consensus_max_pairwise_cost_distance"]])
    assert not diffs, "\n".join(diffs[:30])


@pytest.mark.slow  # ~35 s; one launcher with a file per learner is checked above
def test_two_torchrun_nodes_each_holding_only_its_own_file(tmp_path, simulated):
    """Multi-node torchrun, emulated by two launchers on this machine (static rendezvous,
    fixed --node_rank, node 1 started first), each in a directory that holds only its
    own learner's file under the same relative path: the simulated run's D-ICRL rows and
    history. With the node ranks swapped both learners stop at start-up, each naming the
    file it lacks."""
    import socket

    from dicrl_torch.demos import (
        load_demonstrations,
        partition_demonstrations,
        save_demonstrations,
    )

    if not TORCHRUN.exists():
        pytest.skip(f"no torchrun next to {sys.executable}")
    demos = load_demonstrations(simulated / "demos.npz")
    for v, shard in enumerate(partition_demonstrations(demos, [4, 6])):
        (tmp_path / f"node{v}" / "local").mkdir(parents=True)
        save_demonstrations(tmp_path / f"node{v}" / "local" / f"learner{v}.npz", shard)

    def launch(run_dir: Path, rank_of_node: dict[int, int]) -> list:
        """Both nodes' torchrun, node 1 first; their completed processes, node 0 first."""
        with socket.socket() as sock:
            sock.bind(("127.0.0.1", 0))
            port = sock.getsockname()[1]
        procs = {}
        for node in (1, 0):
            cmd = [str(TORCHRUN), "--nnodes", "2", "--nproc_per_node", "1",
                   "--node_rank", str(rank_of_node[node]), "--master_addr", "127.0.0.1",
                   "--master_port", str(port), str(tiny_train.TRAIN),
                   f"hydra.run.dir={run_dir}", *TINY, "comm=distributed",
                   "algo.run_c_icrl=false",
                   "shard_files=[local/learner0.npz,local/learner1.npz]"]
            # Files, not pipes: a node blocked on a full pipe would stall the other.
            with open(run_dir.parent / f"{run_dir.name}_node{node}.log", "w") as log:
                procs[node] = subprocess.Popen(cmd, cwd=tmp_path / f"node{node}", env=ONE_THREAD,
                                               stdout=log, stderr=subprocess.STDOUT)
        return [subprocess.CompletedProcess(
                    procs[node].args, procs[node].wait(timeout=300), None,
                    (run_dir.parent / f"{run_dir.name}_node{node}.log").read_text())
                for node in (0, 1)]

    run_dir = tmp_path / "run"
    for node, out in enumerate(launch(run_dir, {0: 0, 1: 1})):
        assert out.returncode == 0, f"node {node}: {out.stderr[-3000:]}"
    got, want = (json.loads((p / "results.json").read_text()) for p in (run_dir, simulated))
    assert_unclassified(got, want)
    diffs = differences([got["methods"]["D-ICRL"], got["history"]["D-ICRL"]],
                        [want["methods"]["D-ICRL"], want["history"]["D-ICRL"]])
    assert not diffs, "\n".join(diffs[:30])

    swapped = tmp_path / "swapped"
    for node, out in enumerate(launch(swapped, {0: 1, 1: 0})):
        rank = 1 - node
        assert out.returncode != 0
        assert (f"learner process {rank}: shard_files: no such file local/learner{rank}.npz"
                in out.stderr), out.stderr[-3000:]
    assert not (swapped / "results.json").exists()
