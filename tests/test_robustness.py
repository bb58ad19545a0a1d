"""Robustness: bad configurations refused before computing, checkpoints from another
configuration, SIGTERM/SIGINT and ``kill -9`` followed by ``resume=true``, the privacy
audit of message contents, extreme weights and the NaN/inf guard of the trainer.

The bad-input catalogue of demonstration files, feature bases and graphs is covered in
tests/test_demos_storage.py, tests/test_features.py and tests/test_comm_graphs.py; the
distributed faults in tests/test_comm_distributed.py and tests/test_train_distributed.py.
"""

from __future__ import annotations

import dataclasses
import fractions
import json
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import tiny_dicrl
import torch
from hydra.errors import ConfigCompositionException
from tiny_train import TINY, TRAIN, comparable, compose_train, run_train

from dicrl_torch.algos.dicrl import NonFiniteError, StepSizes
from dicrl_torch.algos.icrl import model_reward
from dicrl_torch.comm import ALLOWED_FIELDS, SimulatedCommunicator
from dicrl_torch.envs.grid import GridLayout, TabularGridModel
from dicrl_torch.features.bases import FactoredFeatures, FeatureBasis
from dicrl_torch.solvers.factored import FactoredSoftBellman

ROOT = Path(__file__).resolve().parents[1]


import common  # noqa: E402 - experiments/ is on pytest's pythonpath
import config_checks  # noqa: E402

from dicrl_torch.runs import checkpoints, signals  # noqa: E402


def training_config(cfg) -> dict:
    """What a checkpoint of the run ``cfg`` must match to resume."""
    return common.run_settings(cfg).training_config


def leftovers(run_dir: Path) -> list[str]:
    """Files a refused or interrupted run must not leave: results and temporary files."""
    return sorted(str(p.relative_to(run_dir)) for p in run_dir.rglob("*")
                  if p.name == "results.json" or p.name.endswith(".tmp"))


@pytest.fixture(scope="module")
def reference(tiny_reference) -> Path:
    """The uninterrupted TINY run that every interrupted-and-resumed run must reproduce."""
    return tiny_reference


# ---------------------------------------------------------------------- configuration
@pytest.mark.parametrize("group,option", [
    ("env", "gridworld"), ("env", "gridworld_open"), ("features/cost", "per_expert"),
    ("features/cost", "local_relu_grid"), ("graph", "ring"), ("comm", "distributed"),
    ("logger", "none"), ("baselines", "greedy"), ("experiment", "table1"),
    ("experiment", "table1_small")])
def test_every_shipped_config_passes_the_checks(group, option):
    common.check_config(compose_train(f"{group}={option}"))


@pytest.mark.parametrize("override,key,must", [
    ("env.layout.n_experts=4", "env.layout.n_experts", "1, 2 or 3"),
    ("env.layout.n_experts=0", "env.layout.n_experts", "1, 2 or 3"),
    ("env.model.horizon=0", "env.model.horizon", "int >= 1"),
    ("env.model.horizon=2.5", "env.model.horizon", "int >= 1"),
    ("env.model.gamma=0", "env.model.gamma", "(0, 1]"),
    ("env.model.gamma=1.5", "env.model.gamma", "(0, 1]"),
    ("env.model.gamma=nan", "env.model.gamma", "(0, 1]"),
    ("algo.threshold=1.5", "algo.threshold", "(0, 1]"),
    ("algo.threshold=0", "algo.threshold", "(0, 1]"),
    ("algo.steps.alpha_bar=0", "algo.steps.alpha_bar", "positive"),
    ("algo.steps.alpha_bar=inf", "algo.steps.alpha_bar", "positive"),
    ("algo.steps.beta_bar=1.5", "algo.steps.beta_bar", "Theorem 1"),
    ("algo.steps.beta_power=0.5", "algo.steps.beta_power", "Theorem 1"),
    ("algo.inner_step=-0.1", "algo.inner_step", "positive"),
    ("algo.inner_steps=1", "algo.inner_steps", "int >= 2"),
    ("algo.outer_iterations=0", "algo.outer_iterations", "int >= 1"),
    ("algo.lsca_curvature=0", "algo.lsca_curvature", "positive"),
    ("algo.init_cost_weights=2", "algo.init_cost_weights", "[0, 1]"),
    ("algo.init_multiplier=nan", "algo.init_multiplier", "finite"),
    ("algo.prune_min_gain=-1", "algo.prune_min_gain", "null"),
    ("algo.inner_method=newton", "algo.inner_method", "gradient_tracking"),
    ("algo.run_c_icrl=maybe", "algo.run_c_icrl", "true or false"),
    ("algo.merge_stateful_inner=maybe", "algo.merge_stateful_inner", "true or false"),
    ("algo.certificate.shard_fits=maybe", "algo.certificate.shard_fits", "true or false"),
    ("eval_episodes=0", "eval_episodes", "int >= 1"),
    ("checkpoint_every=0", "checkpoint_every", "int >= 1"),
    ("seed=-1", "seed", "int >= 0"),
    ("expert_temperature=-1", "expert_temperature", ">= 0"),
    ("baselines.epsilon=-1", "baselines.epsilon", ">= 0"),
    ("baselines.max_constraints=1.5", "baselines.max_constraints", "int >= 0"),
    ("baselines.max_constraints=-2", "baselines.max_constraints", "int >= 0"),
])
def test_out_of_range_values_are_refused_naming_key_and_fix(override, key, must):
    with pytest.raises(config_checks.ConfigError) as info:
        common.check_config(compose_train(override))
    msg = str(info.value)
    value = override.split("=", 1)[1]
    assert f"{key}=" in msg and must in msg and f"set e.g. {key}=" in msg, msg
    assert value.lower() in msg.lower(), msg
    assert "1 problem(s)" in msg  # only the bad key is reported


def test_merge_stateful_inner_reaches_the_trainer():
    """The config's key is a trainer option (off by default: it changes SAC's numbers)."""
    assert common.trainer_spec(compose_train()).kwargs(2)["merge_stateful_inner"] is False
    spec = common.trainer_spec(compose_train("algo.merge_stateful_inner=true"))
    assert spec.kwargs(2)["merge_stateful_inner"] is True


@pytest.mark.parametrize("split,match", [
    ("split=[0,100]", "ints >= 1"),           # a learner shard with zero trajectories
    ("split=[50,-10,60]", "ints >= 1"),
    ("split=[]", "non-empty"),
    ("split=[10,20]", "sums to 30, not n_demonstrations=100"),
])
def test_bad_splits_are_refused(split, match):
    with pytest.raises(config_checks.ConfigError, match=match):
        common.check_config(compose_train(split))


def test_every_problem_is_reported_at_once():
    # One per object a config builds (the task's settings, the model) and per clash of
    # groups; an object names the first of its own values it refuses.
    with pytest.raises(config_checks.ConfigError) as info:
        common.check_config(compose_train("algo.threshold=2", "env.model.gamma=-1",
                                          "split=[10,20]"))
    assert "3 problem(s)" in str(info.value)


def test_unknown_keys_are_refused_with_a_suggestion():
    # Hydra's struct mode refuses a new key outright ...
    with pytest.raises(ConfigCompositionException) as info:
        compose_train("algo.thresold=0.3")
    assert "Could not override 'algo.thresold'" in str(info.value)
    assert "+algo.thresold=0.3" in str(info.value)  # Hydra names the append syntax
    # ... but "+key=value" appends one that nothing would read: refused here.
    with pytest.raises(config_checks.ConfigError) as info:
        common.check_config(compose_train("+algo.thresold=0.3", "+solver.dtyp=float64",
                                          "+seeed=1"))
    msg = str(info.value)
    assert "unknown key 'algo.thresold'" in msg and "did you mean 'threshold'?" in msg
    # a node with a _target_ is checked against the signature of what it builds
    assert "unknown key 'solver.dtyp'" in msg and "FactoredSoftBellman" in msg
    assert "did you mean 'dtype'?" in msg
    assert "unknown key 'seeed'" in msg and "did you mean 'seed'?" in msg


def test_a_refused_run_exits_before_computing_and_writes_nothing(tmp_path):
    out = run_train(tmp_path, "algo.threshold=1.5", "+algo.thresold=0.3")
    assert out.returncode == 2, out.stderr[-2000:]
    assert "error: 2 problem(s) in the configuration, nothing was computed" in out.stderr
    assert "algo.threshold=1.5 is invalid" in out.stderr
    assert "Traceback" not in out.stderr
    assert leftovers(tmp_path) == []
    # nothing but Hydra's own record of the run: no demonstrations, no checkpoint
    assert {p.name for p in tmp_path.iterdir()} <= {".hydra", "train.log"}


# ---------------------------------------------------------------------- checkpoints
@pytest.fixture(scope="module")
def tiny():
    return tiny_dicrl.build_tiny()


def test_a_checkpoint_from_another_configuration_is_refused(tmp_path, tiny):
    t = tiny_dicrl.make_trainer(tiny)
    t.train(1)
    path = tmp_path / "checkpoint.pt"
    config = training_config(compose_train(*TINY))
    checkpoints.Checkpoints(path, False, config=config).save("D-ICRL", t)
    assert [p.name for p in tmp_path.iterdir()] == ["checkpoint.pt"]  # no .tmp left
    # the same configuration resumes, also with a longer training or another threshold
    for same in ([], ["algo.outer_iterations=30", "algo.threshold=0.4", "eval_episodes=5"]):
        ck = checkpoints.Checkpoints(path, True, config=training_config(
            compose_train(*TINY, *same)))
        assert ck.states("D-ICRL")[0]["outer_iteration"] == 1
    other = training_config(compose_train(*TINY, "seed=1", "algo.steps.alpha_bar=0.05"))
    with pytest.raises(ValueError) as info:
        checkpoints.Checkpoints(path, True, config=other)
    msg = str(info.value)
    assert "different configuration" in msg and "seed: 0 in the checkpoint, 1 now" in msg
    assert "algo.steps.alpha_bar: 0.12 in the checkpoint, 0.05 now" in msg  # quick's 0.12
    assert "without resume=true" in msg
    # a trainer of another shape refuses the state itself (the trainer's own check)
    other_k = tiny_dicrl.make_trainer(tiny)
    other_k.K = 4
    with pytest.raises(ValueError, match="differently configured trainer"):
        other_k.load_state_dict(t.state_dict())


def test_the_planner_of_the_evaluation_is_not_part_of_a_checkpoints_config(tmp_path, tiny):
    """eval_policy=plan's planner acts after training only: a finished run resumes to be
    evaluated with another planner, and a checkpoint of an older release, which recorded
    solver.planner.*, still resumes."""
    flat = checkpoints.training_config({"seed": 0, "solver": {
        "timesteps": 500, "planner": {"knot": 5, "replan": 1}}})
    assert flat == {"seed": 0, "solver.timesteps": 500}
    t = tiny_dicrl.make_trainer(tiny)
    t.train(1)
    path = tmp_path / "checkpoint.pt"
    config = training_config(compose_train(*TINY))
    older = {**config, "solver.planner.knot": 5, "solver.planner.samples": 256}
    checkpoints.Checkpoints(path, False, config=older).save("D-ICRL", t)
    ck = checkpoints.Checkpoints(path, True, config=config)
    assert ck.states("D-ICRL")[0]["outer_iteration"] == 1
    with pytest.raises(ValueError, match="different configuration"):
        checkpoints.Checkpoints(path, True, config={**config, "seed": 1})


def test_a_checkpoint_older_than_a_key_reads_as_its_former_behaviour(tmp_path, tiny):
    """algo.merge_stateful_inner came after checkpoints were written: one without it holds
    the unmerged training, so it resumes under false and is refused under true."""
    t = tiny_dicrl.make_trainer(tiny)
    t.train(1)
    path = tmp_path / "checkpoint.pt"
    config = training_config(compose_train(*TINY))
    assert config["algo.merge_stateful_inner"] is False
    older = {k: v for k, v in config.items() if k != "algo.merge_stateful_inner"}
    checkpoints.Checkpoints(path, False, config=older).save("D-ICRL", t)
    assert checkpoints.Checkpoints(path, True, config=config).states("D-ICRL")
    with pytest.raises(ValueError, match="algo.merge_stateful_inner: False in the checkpoint"):
        checkpoints.Checkpoints(path, True,
                                config={**config, "algo.merge_stateful_inner": True})


@pytest.mark.parametrize("content", [b"", b"not a checkpoint", b"PK\x03\x04truncated"])
def test_an_unreadable_checkpoint_is_refused(tmp_path, content):
    path = tmp_path / "checkpoint.pt"
    path.write_bytes(content)
    with pytest.raises(ValueError, match=r"cannot be read as a checkpoint.*Delete it"):
        checkpoints.Checkpoints(path, True)


def test_a_checkpoint_with_pickled_objects_is_refused(tmp_path):
    path = tmp_path / "checkpoint.pt"
    # an arbitrary object: only unpickling (running its reduce code) could restore it
    torch.save({"D-ICRL": {"outer_iteration": 1, "payload": fractions.Fraction(1, 3)}}, path)
    with pytest.raises(ValueError, match="cannot be read as a checkpoint"):
        checkpoints.Checkpoints(path, True)
    torch.save([1, 2, 3], path)
    with pytest.raises(ValueError, match="not a checkpoint of this program"):
        checkpoints.Checkpoints(path, True)


# ---------------------------------------------------------------------- crashes
def test_a_second_signal_stops_at_once():
    stop = signals.StopOnSignal()
    with pytest.raises(signals.Interrupted):  # outside training: at once
        stop._handle(signal.SIGINT, None)
    stop.training = True
    stop._handle(signal.SIGTERM, None)  # first: finish the outer iteration
    assert stop.signum == signal.SIGTERM
    with pytest.raises(signals.Interrupted) as info:
        stop._handle(signal.SIGTERM, None)
    assert info.value.signum == signal.SIGTERM and info.value.saved is None
    with signals.StopOnSignal() as s:  # installs its handlers and restores the previous
        assert signal.getsignal(signal.SIGTERM) == s._handle
    assert signal.getsignal(signal.SIGTERM) != s._handle


def test_sigterm_checkpoints_and_the_printed_command_resumes(tmp_path, reference):
    run_dir = tmp_path / "run"
    # the process sends itself SIGTERM right after checkpointing outer iteration 1
    stopped = run_train(run_dir, env={"DICRL_CRASH_AFTER": "D-ICRL:1",
                                      "DICRL_CRASH_SIGNAL": "TERM"})
    assert stopped.returncode == 128 + signal.SIGTERM, stopped.stderr[-3000:]
    err = stopped.stderr
    assert "SIGTERM received: stopping after this outer iteration" in err
    assert "interrupted by SIGTERM (checkpoint D-ICRL saved after outer iteration 1)" in err
    assert leftovers(run_dir) == []
    saved = torch.load(run_dir / "checkpoint.pt", weights_only=True)
    assert saved["D-ICRL"]["outer_iteration"] == 1
    command = err.strip().splitlines()[-1].strip()
    assert err.strip().splitlines()[-2].endswith("Resume with:")
    argv = shlex.split(command)
    assert argv[-2:] == ["resume=true", f"hydra.run.dir={run_dir}"]
    resumed = subprocess.run(argv, capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert "outer iterations done: {'D-ICRL': 1}" in resumed.stdout
    assert comparable(run_dir) == comparable(reference)


def test_kill_9_at_a_random_outer_iteration_then_resume(tmp_path, reference):
    rng = np.random.default_rng(20240611)
    method = str(rng.choice(["D-ICRL", "C-ICRL"]))  # the trainer and outer iteration
    n = int(rng.integers(1, 4))                     # after whose checkpoint it dies
    crashed = run_train(tmp_path, env={"DICRL_CRASH_AFTER": f"{method}:{n}"})
    assert crashed.returncode == -9, (method, n, crashed.stderr[-2000:])
    assert not (tmp_path / "results.json").exists()
    resumed = run_train(tmp_path, "resume=true")
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert comparable(tmp_path) == comparable(reference), (method, n)


@pytest.mark.slow  # ~1 min: several random moments, signals sent from outside
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_kill_9_or_sigint_at_a_random_moment_then_resume(tmp_path, reference, seed):
    rng = np.random.default_rng(seed)
    sig = signal.SIGKILL if seed != 1 else signal.SIGINT
    proc = subprocess.Popen(
        [sys.executable, str(TRAIN), f"hydra.run.dir={tmp_path}",
         *TINY, "algo.outer_iterations=3"], cwd=ROOT, stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True)
    time.sleep(float(rng.uniform(3.0, 9.0)))  # start-up takes ~4 s on 2 cores
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    if sig == signal.SIGINT and proc.returncode != 0:
        assert proc.returncode == 128 + signal.SIGINT, err[-2000:]
        assert "Resume with:" in err
    resumed = run_train(tmp_path, "resume=true")
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert comparable(tmp_path) == comparable(reference)


# ---------------------------------------------------------------------- C-ICRL in its own job
def test_c_icrl_trained_in_its_own_job_merges_into_the_run(tmp_path, reference):
    # The run stops after D-ICRL; C-ICRL trains meanwhile in a job of its own.
    run, own = tmp_path / "run", tmp_path / "own"
    crashed = run_train(run, env={"DICRL_CRASH_AFTER": "D-ICRL:3"})
    assert crashed.returncode == -9
    alone = run_train(own, "algo.run_d_icrl=false")
    assert alone.returncode == 0, alone.stderr[-3000:]
    assert "consensus" not in alone.stdout  # no D-ICRL, so no disagreement to print
    res = comparable(own)
    assert list(res["methods"]) == ["C-ICRL", "Experts (ground truth)", "Experts (nominal)"]
    assert res["consensus_max_pairwise_cost_distance"] is None
    assert res["methods"]["C-ICRL"] == comparable(reference)["methods"]["C-ICRL"]

    merged = subprocess.run(
        [sys.executable, "-m", "dicrl_torch.runs.checkpoints", "merge",
         str(own / "checkpoint.pt"), str(run / "checkpoint.pt"), "--method", "C-ICRL"],
        capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert merged.returncode == 0, merged.stderr
    assert "C-ICRL now after outer iteration 3" in merged.stdout
    resumed = run_train(run, "resume=true")
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert "{'D-ICRL': 3, 'C-ICRL': 3}" in resumed.stdout
    # its own job's evaluated rows came along: not pruned and rolled out again
    assert "C-ICRL: rows evaluated after outer iteration 3 taken from" in resumed.stdout
    assert comparable(run) == comparable(reference)


def test_a_run_stopped_after_evaluating_resumes_without_evaluating_again(tmp_path, reference):
    # killed right after D-ICRL's rows were checkpointed, before C-ICRL trains
    crashed = run_train(tmp_path, env={"DICRL_CRASH_AFTER": "D-ICRL:evaluated:3"})
    assert crashed.returncode == -9, crashed.stderr[-2000:]
    saved = torch.load(tmp_path / "checkpoint.pt", weights_only=True)
    expected = comparable(reference)["methods"]["D-ICRL"]["learners"]
    # the rows as evaluated; the run's end adds the identifiability fields to every row,
    # and the learners' traffic
    from dicrl_torch.runs.grid import ANNOTATIONS
    from dicrl_torch.runs.runner import TRAFFIC_KEYS

    assert saved["D-ICRL:evaluated"]["rows"] == [
        {k: v for k, v in row.items() if k not in (*ANNOTATIONS, *TRAFFIC_KEYS)}
        for row in expected]
    resumed = run_train(tmp_path, "resume=true")
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert "D-ICRL: rows evaluated after outer iteration 3 taken from" in resumed.stdout
    assert "outer iterations done: {'D-ICRL': 3})" in resumed.stdout  # rows: no trainer
    assert comparable(tmp_path) == comparable(reference)
    # rows of other evaluation settings are not taken: they are evaluated anew
    other = run_train(tmp_path, "resume=true", "eval_episodes=12")
    assert other.returncode == 0, other.stderr[-3000:]
    assert "rows evaluated after" not in other.stdout
    assert comparable(tmp_path)["methods"]["D-ICRL"]["learners"] != expected


# ---------------------------------------------------------------------- greedy baselines
@pytest.fixture(scope="module")
def reference_greedy(tmp_path_factory) -> Path:
    """The uninterrupted TINY run with both greedy baselines."""
    run_dir = tmp_path_factory.mktemp("reference_greedy")
    out = run_train(run_dir, "baselines=greedy")
    assert out.returncode == 0, out.stderr[-3000:]
    saved = torch.load(run_dir / "checkpoint.pt", weights_only=True)
    for name in ("ME-greedy", "MCE-greedy"):  # saved after each of its 5 candidates, and done
        assert saved[name]["greedy"]["finished"] and saved[name]["outer_iteration"] == 6
    return run_dir


# SIGTERM's checkpoint is checked on D-ICRL below; ME's path differs from MCE's in its loss only.
@pytest.mark.parametrize("crash, sig", [
    ("MCE-greedy:2", "KILL"), pytest.param("ME-greedy:3", "TERM", marks=pytest.mark.slow)])
def test_greedy_baseline_stopped_mid_search_resumes_where_it_was(tmp_path, reference_greedy,
                                                                  crash, sig):
    stopped = run_train(tmp_path, "baselines=greedy",
                        env={"DICRL_CRASH_AFTER": crash, "DICRL_CRASH_SIGNAL": sig})
    assert stopped.returncode == (-9 if sig == "KILL" else 128 + signal.SIGTERM)
    assert not (tmp_path / "results.json").exists()
    name, n = crash.split(":")
    if sig == "TERM":
        assert f"checkpoint {name} saved at {n} candidates evaluated" in stopped.stderr
    before = torch.load(tmp_path / "checkpoint.pt", weights_only=True)[name]["greedy"]
    resumed = run_train(tmp_path, "baselines=greedy", "resume=true")
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert f"{name} at {n} candidates evaluated)" in resumed.stdout
    assert comparable(tmp_path) == comparable(reference_greedy)
    # The baseline's training time counts the stopped process's candidates too.
    after = torch.load(tmp_path / "checkpoint.pt", weights_only=True)[name]["greedy"]
    training_s = json.loads((tmp_path / "results.json").read_text())["training_s"]
    assert {"ME-greedy", "MCE-greedy"} <= set(training_s)
    assert training_s[name] >= after["seconds"] > before["seconds"] > 0


@pytest.mark.slow  # ~12 s; the merge of a job of its own: C-ICRL's test above
def test_greedy_baselines_in_a_job_of_their_own_merge_into_the_run(tmp_path, reference_greedy,
                                                                   capsys):
    run, own = tmp_path / "run", tmp_path / "own"
    crashed = run_train(run, "baselines=greedy", env={"DICRL_CRASH_AFTER": "C-ICRL:3"})
    assert crashed.returncode == -9
    alone = run_train(own, "baselines=greedy", "algo.run_d_icrl=false", "algo.run_c_icrl=false")
    assert alone.returncode == 0, alone.stderr[-3000:]
    assert list(comparable(own)["methods"]) == [
        "ME-greedy", "MCE-greedy", "Experts (ground truth)", "Experts (nominal)"]
    # the merge command in this process (its command line runs in the C-ICRL test above)
    checkpoints.main(["merge", str(own / "checkpoint.pt"), str(run / "checkpoint.pt"),
                      "--method", "ME-greedy", "--method", "MCE-greedy"])
    assert "ME-greedy now at 5 candidates evaluated, finished" in capsys.readouterr().out
    resumed = run_train(run, "baselines=greedy", "resume=true")
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert "ME-greedy:" not in resumed.stderr  # no greedy step ran again: no progress bar
    assert comparable(run) == comparable(reference_greedy)


def test_merge_refuses_missing_stale_and_foreign_states(tmp_path):
    def checkpoint(name: str, **states: tuple[int, dict]) -> Path:
        path = tmp_path / name
        torch.save({k.replace("_", "-"): {"outer_iteration": n, "run_config": config}
                    for k, (n, config) in states.items()}, path)
        return path

    ours = {"seed": 0, "algo.inner_steps": 2}
    run = checkpoint("run.pt", D_ICRL=(3, ours), C_ICRL=(1, ours))
    with pytest.raises(ValueError, match="holds no C-ICRL state"):
        checkpoints.merge(checkpoint("none.pt", D_ICRL=(3, ours)), run, ["C-ICRL"])
    with pytest.raises(ValueError, match="already holds C-ICRL after outer iteration 1"):
        checkpoints.merge(checkpoint("early.pt", C_ICRL=(1, ours)), run, ["C-ICRL"])
    with pytest.raises(ValueError, match=r"another configuration .*seed: 1 there, 0 here"):
        checkpoints.merge(checkpoint("other.pt", C_ICRL=(3, {**ours, "seed": 1})), run,
                          ["C-ICRL"])
    (tmp_path / "junk.pt").write_text("not a checkpoint")
    with pytest.raises(ValueError, match="cannot be read as a checkpoint"):
        checkpoints.merge(tmp_path / "junk.pt", run, ["C-ICRL"])
    assert torch.load(run, weights_only=True)["C-ICRL"]["outer_iteration"] == 1  # untouched
    assert checkpoints.merge(checkpoint("done.pt", C_ICRL=(3, ours)), run, ["C-ICRL"]) == {
        "C-ICRL": 3}
    saved = torch.load(run, weights_only=True)
    assert (saved["D-ICRL"]["outer_iteration"], saved["C-ICRL"]["outer_iteration"]) == (3, 3)


def test_run_d_icrl_false_is_refused_where_it_cannot_run():
    with pytest.raises(config_checks.ConfigError, match="nothing to run; use comm=simulated"):
        common.check_config(compose_train(*TINY, "comm=distributed", "algo.run_d_icrl=false"))
    with pytest.raises(config_checks.ConfigError, match="greedy baseline without its reward"):
        common.check_config(compose_train("experiment=table2_quick", "algo.run_d_icrl=false"))
    # without the baseline the arena's C-ICRL alone runs, in one process (the drone
    # configs ship comm=distributed, which has no learner process to start then)
    common.check_config(compose_train("experiment=table2_quick", "algo.run_d_icrl=false",
                                      "baselines=none", "comm=simulated"))
    with pytest.raises(config_checks.ConfigError, match="use comm=simulated"):
        common.check_config(compose_train("experiment=table2_quick",
                                          "algo.run_d_icrl=false", "baselines=none"))
    with pytest.raises(config_checks.ConfigError, match="algo.run_d_icrl='no' is invalid"):
        common.check_config(compose_train(*TINY, "algo.run_d_icrl=no"))


# ---------------------------------------------------------------------- privacy
class ContentRecorder(SimulatedCommunicator):
    """Keeps a copy of every value sent, not only its field and shape."""

    def __init__(self, n_learners: int) -> None:
        super().__init__(n_learners, record=True)
        self.sent: list[tuple[str, torch.Tensor]] = []

    def all_gather(self, values, field, phase=None):
        out = super().all_gather(values, field, phase)
        self.sent.extend((field, row.clone()) for row in values)
        return out


@pytest.mark.parametrize("inner_method", ["paper", "tracking", "gradient_tracking"])
def test_messages_hold_only_documented_fields_and_no_local_statistics(tiny, inner_method):
    comm = ContentRecorder(len(tiny_dicrl.SPLIT))
    # one shared initial ω_c: one inner process serves all learners (fast; tested equal)
    t = tiny_dicrl.make_trainer(tiny, communicator=comm, inner_method=inner_method,
                                init_cost=0.3)
    t.train(2)
    t.disagreement()
    t.network_or(torch.stack([st.cost_accrual > 0 for st in t.stats]))  # the certificate's
    d, p = t.learner_model.cost_dim, t.learner_model.reward_dim + 1
    sizes = {"eta": (p,), "cost_weights": (d,), "tracker": (d,), "inner_tracker": (p,),
             "lsca_target": (d,), "demonstrated": (-(-d // 52),)}  # 52 mask bits a word
    assert set(sizes) == set(ALLOWED_FIELDS)
    fields = {f for f, _ in comm.sent}
    expected = {"eta", "cost_weights", "tracker", "demonstrated"} | (
        {"inner_tracker"} if inner_method != "paper" else set())
    assert fields == expected
    assert len(comm.sent) == len(comm.messages)
    private = [x for st in t.stats for x in (st.mu_r_hat, st.cost_accrual)]
    for field, value in comm.sent:
        assert tuple(value.shape) == sizes[field] and value.dtype == torch.float64
        # neither μ̂_r nor the cost accrual (b̂ = ω_c · accrual) of any learner
        for x in private:
            assert not (value.shape == x.shape and torch.allclose(value, x)), field


# ---------------------------------------------------------------------- numerics
@pytest.mark.parametrize("lam", [1e6, -1e6])
@pytest.mark.parametrize("reward_weight", [1.0, 1e6])
def test_extreme_weights_give_finite_values_policies_and_occupancies(tiny, lam,
                                                                      reward_weight):
    solver, rb, cb, _ = tiny
    fr, fc = rb(), cb()
    reward = model_reward(fr, fc, torch.full((fr.dim,), reward_weight, dtype=torch.float64),
                          lam, torch.full((fc.dim,), 0.5, dtype=torch.float64))
    sol = solver.solve(reward)  # float64
    m = solver.model
    assert torch.isfinite(sol.V).all()
    cells = torch.cartesian_prod(*[torch.arange(m.n_cells)] * m.n_experts)
    for t in (0, m.horizon - 1):
        pi = sol.policy_at(t, cells)
        assert torch.isfinite(pi).all()
        assert torch.allclose(pi.sum(1), torch.ones(len(cells), dtype=pi.dtype))
    discounted_steps = sum(m.gamma**t for t in range(m.horizon))
    assert torch.isfinite(sol.local_occupancy).all()
    assert torch.isfinite(sol.state_occupancy).all()
    assert torch.allclose(sol.local_occupancy.sum((1, 2)),
                          torch.full((m.n_experts,), discounted_steps, dtype=torch.float64))


@pytest.mark.parametrize("kw", [{"init_multiplier": 1e6}, {"init_multiplier": -1e6},
                                {"init_reward_weights": 1e6}])
def test_the_trainer_stays_finite_at_extreme_weights(tiny, kw):
    t = tiny_dicrl.make_trainer(tiny, **kw)
    t.train(2)
    for x in (t.state.cost_weights, t.state.eta_bar, t.state.tracker):
        assert torch.isfinite(x).all()


def poison(t, learner: int) -> None:
    """Give local learner ``learner`` an infinite μ̂_r: its next dual gradient is inf."""
    st = t.stats[learner]
    t.stats[learner] = dataclasses.replace(st, mu_r_hat=torch.full_like(st.mu_r_hat,
                                                                        float("inf")))


def test_nan_or_inf_stops_the_run_naming_iteration_step_and_learner(tiny):
    t = tiny_dicrl.make_trainer(tiny)
    t.train(1)
    before = t.state_dict()
    poison(t, 2)
    with pytest.raises(NonFiniteError) as info:
        t.train(3)
    msg = str(info.value)
    assert isinstance(info.value, FloatingPointError)
    assert "dual gradient m ∇G of learner 2" in msg
    assert "outer iteration 1, inner step 0" in msg
    assert "inner process for learner 0's ω_c" in msg
    assert "Lower the step sizes" in msg and "solver.dtype=float64" in msg
    assert "float32" not in msg  # the tiny solver already computes in float64
    # the state is not advanced past the last finite iteration
    assert t.state.outer_iteration == 1
    assert torch.equal(t.state.cost_weights, before["cost_weights"])


def test_an_overflowing_multiplier_is_caught(tiny):
    t = tiny_dicrl.make_trainer(tiny, init_multiplier=-1e300)
    with pytest.raises(NonFiniteError, match=r"learner \d is not finite .* at outer "
                                             r"iteration 0, inner step 0"):
        t.train(1)


def test_a_float32_solver_is_named_in_the_hint(tiny):
    solver, rb, cb, shards = tiny
    f32 = FactoredSoftBellman(model=solver.model, dtype=torch.float32)
    t = tiny_dicrl.make_trainer((f32, rb, cb, shards), inner_method="gradient_tracking")
    poison(t, 0)
    with pytest.raises(NonFiniteError, match="computes in float32.*overflows"):
        t.train(1)


@pytest.mark.parametrize("kw,match", [
    ({"init_multiplier": float("nan")}, "init_multiplier"),
    ({"init_reward_weights": float("inf")}, "init_reward_weights"),
    ({"init_cost": float("nan")}, "init_cost_weights"),
])
def test_non_finite_initial_values_are_refused_before_computing(tiny, kw, match):
    with pytest.raises(ValueError, match=match):
        tiny_dicrl.make_trainer(tiny, **kw)
    with pytest.raises(ValueError, match="alpha_bar"):
        StepSizes(alpha_bar=float("nan"))


def test_a_run_that_turns_non_finite_exits_non_zero_without_results(tmp_path):
    out = run_train(tmp_path, "algo.steps.alpha_bar=1e308")  # η overflows at once
    assert out.returncode == 1, out.stderr[-2000:]
    assert "error: " in out.stderr and "is not finite (NaN or inf) at outer iteration 0" in (
        out.stderr)
    assert "η = [ω_r, λ] of learner 0" in out.stderr and "inner step 0" in out.stderr
    assert "Lower the step sizes" in out.stderr and "Traceback" not in out.stderr
    assert leftovers(tmp_path) == []


# ---------------------------------------------------------------------- feature bases
class BadBasis(FeatureBasis):
    """A cost basis whose table is whatever the test gives it."""

    def __init__(self, model, local, joint=None, dim=None):
        super().__init__(model)
        self.names = [f"f{j}" for j in range(dim or local.shape[-1])]
        self._local, self._joint = local, joint

    def build(self):
        if self._joint is None:
            return FactoredFeatures(local=self._local)
        return FactoredFeatures(local=self._local, joint=self._joint,
                                joint_columns=torch.tensor([0]))


@pytest.fixture(scope="module")
def grid_model():
    return TabularGridModel(layout=GridLayout.open_grid(3, 2), horizon=3)


@pytest.mark.parametrize("case,match", [
    ("above", r"leave \[0, 1.0\].*rescale"), ("negative", r"leave \[0, 1.0\]"),
    ("nan", "non-finite"), ("inf", "non-finite"), ("width", "expected"),
    ("joint", r"leave \[0, 1.0\]")])
def test_a_basis_outside_0_d_or_of_the_wrong_width_is_refused(grid_model, case, match):
    m = grid_model
    shape = (m.n_experts, m.n_cells, m.n_actions, 2)
    local = torch.zeros(shape, dtype=torch.float64)
    joint, dim = None, None
    if case == "above":
        local[0, 0, 0, 1] = 0.8
        local[1, 3, 0, 1] = 0.8  # each term <= 1, but their sum reaches 1.6 > max_value
    elif case == "negative":
        local[1, 2, 3, 0] = -0.1
    elif case in ("nan", "inf"):
        local[0, 0, 0, 0] = float(case)
    elif case == "width":
        dim = 3  # names say 3 features, the table holds 2
    else:
        local[0, 0, 0, 0] = 0.5
        joint = torch.zeros(m.n_states, 1, dtype=torch.float64)
        joint[4] = 0.7  # 0.5 + 0.7 on feature 0
    with pytest.raises(ValueError, match=match):
        BadBasis(m, local, joint, dim)()


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """Demonstrations recorded on the single-expert 9x9 layout with T = 8: 3 + 4 files."""
    from dicrl_torch.demos import partition_demonstrations, save_demonstrations
    from dicrl_torch.envs.grid import GridLayout, TabularGridModel
    from dicrl_torch.features.bases import GoalClosenessRewardBasis
    from dicrl_torch.solvers.experts import expert_solution, sample_trajectories
    from dicrl_torch.solvers.factored import FactoredSoftBellman

    d = tmp_path_factory.mktemp("recorded")
    model = TabularGridModel(layout=GridLayout.scobee(n_experts=1), horizon=8)
    rb = GoalClosenessRewardBasis(model)
    experts = expert_solution(solver=FactoredSoftBellman(model=model), reward_features=rb(),
                              reward_weights=rb.true_weights())
    demos = sample_trajectories(experts, 7, np.random.default_rng(0))
    return [str(save_demonstrations(d / f"learner{v}.npz", s))
            for v, s in enumerate(partition_demonstrations(demos, [3, 4]))]


ONE_EXPERT = ["env.layout.n_experts=1", "env.model.horizon=8", "n_demonstrations=7",
              "split=[3,4]"]


def files_override(files):
    return f"shard_files=[{','.join(files)}]"


@pytest.mark.parametrize("extra,match", [
    (["split=[2,5]"], r"hold \[3, 4\] trajectories.*set split=\[3,4\] n_demonstrations=7"),
    (["env.model.horizon=9"], r"learner0\.npz.*horizon"),
    (["env.layout.n_experts=2", "env.model.horizon=8"], r"learner0\.npz.*n_experts"),
])
def test_shard_files_that_do_not_fit_the_run_are_refused_before_any_solve(recorded, extra,
                                                                           match):
    cfg = compose_train(*ONE_EXPERT, files_override(recorded), *extra)
    common.check_config(cfg)  # the paths are fine; their contents are not
    with pytest.raises(ValueError, match=match):
        common.grid_task(cfg)


def test_shard_files_from_another_start_are_refused(recorded, tmp_path):
    from dicrl_torch.demos import load_demonstrations, save_demonstrations
    from dicrl_torch.demos.storage import Demonstrations

    d = load_demonstrations(recorded[1])
    states = d.states.copy()
    states[2, 0, 0] = 40  # trajectory 2 starts in the centre cell, not in (0, 8)
    moved = save_demonstrations(tmp_path / "moved.npz", Demonstrations(
        states=states, actions=d.actions, n_cells=d.n_cells, n_actions=d.n_actions))
    cfg = compose_train(*ONE_EXPERT, files_override([recorded[0], str(moved)]))
    with pytest.raises(ValueError, match=r"moved\.npz': trajectory 2 starts in cells \[40\]"):
        common.grid_task(cfg)


@pytest.mark.parametrize("files,match", [
    (lambda r: [r[0]], r"lists 1 files but split=\[3, 4\] has 2 learners"),
    (lambda r: [r[0], r[0]], "lists a file twice"),
    (lambda r: [r[0], "nowhere.npz"], "no such file nowhere.npz"),
])
def test_shard_file_lists_are_checked_with_the_config(recorded, files, match):
    with pytest.raises(config_checks.ConfigError, match=match):
        common.check_config(compose_train(*ONE_EXPERT, files_override(files(recorded))))


def test_shard_files_are_refused_for_the_arena(recorded):
    with pytest.raises(config_checks.ConfigError, match="shard_files is for the grid world"):
        common.check_config(
            compose_train("experiment=table2_quick", files_override(recorded)))


def test_the_command_line_refuses_a_shard_file_misfit_at_start_up(recorded, tmp_path):
    out = run_train(tmp_path, *ONE_EXPERT, files_override(recorded), "split=[4,3]")
    assert out.returncode == 2, out.stderr[-2000:]
    assert "error: shard_files hold [3, 4] trajectories" in out.stderr
    assert "Traceback" not in out.stderr and not (tmp_path / "results.json").exists()


@pytest.mark.parametrize("rank,extra,reads", [
    (None, [], [0, 1]),                                  # one process holds every learner
    ("1", [], [1]),                                      # a torchrun learner: its own file
    ("0", [], [0, 1]),                                   # rank 0 pools them for C-ICRL
    ("0", ["algo.run_c_icrl=false"], [0]),               # ... unless nothing is pooled
    ("0", ["algo.run_c_icrl=false", "baselines=greedy"], [0, 1]),
])
def test_each_process_reads_only_the_shard_files_it_needs(recorded, monkeypatch, rank, extra,
                                                          reads):
    comm = [] if rank is None else ["comm=distributed"]
    if rank is not None:
        monkeypatch.setenv("RANK", rank)
        monkeypatch.setenv("WORLD_SIZE", "2")
    cfg = compose_train(*ONE_EXPERT, *comm, *extra, files_override(recorded))
    assert common.shard_files_read_by(cfg, common.torchrun_rank(cfg)) == reads


def test_a_learner_process_needs_only_its_own_shard_file(recorded, monkeypatch):
    """Learner 1's machine lacks learner 0's file: learner 1 runs; rank 0, which pools the
    files for C-ICRL, is refused with the fix."""
    files = ["elsewhere/learner0.npz", recorded[1]]
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("RANK", "1")
    cfg = compose_train(*ONE_EXPERT, "comm=distributed", files_override(files))
    common.check_config(cfg)
    common.check_shard_contents(cfg)
    p = common.grid_task(cfg, rank=1)
    assert p.shards[0] is None and p.demos is None
    assert p.experts is None and p.nominal is None  # only rank 0 writes the expert rows
    assert p.shards[1].n_trajectories == 4
    monkeypatch.setenv("RANK", "0")
    with pytest.raises(config_checks.ConfigError,
                       match=r"learner process 0: shard_files: no such file "
                             r"elsewhere/learner0\.npz.*algo\.run_c_icrl=false baselines=none"):
        common.check_config(cfg)


def test_a_checkpoint_of_other_shard_files_is_refused(recorded, tmp_path):
    """Resuming on demonstration files with other contents would continue training on
    other data; the same contents (also under another path) resume. Runs without
    shard_files keep their configuration as before (older checkpoints stay valid)."""
    import shutil

    sampled = training_config(compose_train(*ONE_EXPERT))
    assert not any(k.startswith("shard_files") for k in sampled)
    own = training_config(compose_train(*ONE_EXPERT, files_override(recorded)))
    copy = str(shutil.copy(recorded[1], tmp_path / "copy.npz"))
    same = training_config(compose_train(*ONE_EXPERT,
                                               files_override([recorded[0], copy])))
    swapped = training_config(compose_train(*ONE_EXPERT, "split=[4,3]",
                                                  files_override(recorded[::-1])))
    assert own["shard_files.sha256"] == same["shard_files.sha256"]
    assert own["shard_files.sha256"] != swapped["shard_files.sha256"]
    path = tmp_path / "checkpoint.pt"
    checkpoints.Checkpoints(path, False, config=own).save("D-ICRL", tiny_dicrl.make_trainer(
        tiny_dicrl.build_tiny()))
    checkpoints.Checkpoints(path, True, config=same)
    with pytest.raises(ValueError, match="shard_files.sha256"):
        checkpoints.Checkpoints(path, True, config=swapped)
