"""Every config group composes and every ``_target_`` instantiates (no key silently
goes nowhere); the demo entry point runs end to end."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import OmegaConf
from tiny_train import TINY, TRAIN, comparable, run_train, train_here

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
sys.path.insert(0, str(ROOT / "experiments"))
from common import drone_env_factory  # noqa: E402

# What marks an option of a continuous game in its YAML (a drone, continuous or MPE
# basis, an arena, the SAC solver, the SAC tasks' greedy row); every other option is the
# grid world's, but baselines=none, which fits both.
DRONE_MARKERS = ("features.drone", "features.continuous", "features.mpe", "features.local",
                 "arena:", "solvers.sac", "M(C)E-greedy")


def group_options(group: str, world: str | None = None) -> list[str]:
    """The options of a config group; with ``world``, only the grid world's ("grid") or
    the continuous games' ("drones": the arena and the MPE spread)."""
    paths = sorted((CONFIGS / group).glob("*.yaml"))
    if world is not None:
        def is_drone(text):
            return any(m in text for m in DRONE_MARKERS)
        paths = [p for p in paths if is_drone(p.read_text()) == (world == "drones")]
    return [p.stem for p in paths]


def build(cfg, **objects):
    return instantiate(cfg, _partial_=True)(**objects)


@pytest.mark.parametrize("env", group_options("env", "grid"))
@pytest.mark.parametrize("cost", group_options("features/cost", "grid"))
@pytest.mark.parametrize("reward", group_options("features/reward", "grid"))
def test_every_target_instantiates(env, cost, reward):
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        cfg = compose(config_name="demo", overrides=[
            f"env={env}", f"features/cost={cost}", f"features/reward={reward}",
            "env.model.horizon=3"])
    layout = instantiate(cfg.env.layout)
    model = build(cfg.env.model, layout=layout)
    solver = build(cfg.solver, model=model)
    rb = build(cfg.features.reward, model=model)
    cb = build(cfg.features.cost, model=model)
    assert rb().dim == rb.dim and cb().dim == cb.dim
    sol = solver.solve(rb().weighted(rb.true_weights(tuple(cfg.env.true_reward_weights))))
    assert sol.feature_expectation(cb()).shape == (cb.dim,)
    # every _target_ in the composed config was consumed above
    targets = [k for k in OmegaConf.to_yaml(cfg).splitlines() if "_target_" in k]
    assert len(targets) >= 5


@pytest.mark.parametrize("cost", group_options("features/cost", "drones"))
@pytest.mark.parametrize("reward", group_options("features/reward", "drones"))
def test_every_drone_target_instantiates(cost, reward):
    assert group_options("env", "drones") == ["drones", "mpe_spread"]
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        cfg = compose(config_name="train", overrides=[
            "experiment=table2_quick", f"features/cost={cost}", f"features/reward={reward}"])
    rb, cb = instantiate(cfg.features.reward), instantiate(cfg.features.cost)
    cfg.env.arena.max_steps = 5
    solver = build(cfg.solver.solver, reward_basis=rb, cost_basis=cb, seed=0,
                   env_factory=drone_env_factory(cfg))  # the runs' own factory
    sol = solver.solve([0.0] * rb.dim + [-1.0], [0.0] * cb.dim, 0, n_eval_episodes=1)
    assert sol.mu_r.shape == (rb.dim,) and sol.mu_c.shape == (cb.dim,)
    if callable(getattr(cb, "true_constraints", None)):  # a network basis has no truth
        assert cb.true_constraints().shape == (cb.dim,)


def test_demo_runs_end_to_end(tmp_path):
    out = subprocess.run(
        [sys.executable, str(ROOT / "experiments" / "demo_foundation.py"),
         f"hydra.run.dir={tmp_path}", "env.model.horizon=12", "eval_episodes=20",
         "n_demonstrations=20", "split=[5,15]"],
        capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    res = json.loads((tmp_path / "results.json").read_text())
    assert set(res["methods"]) == {"Experts (ground truth)", "Experts (nominal)"}
    assert res["methods"]["Experts (ground truth)"]["learners"][0]["CVR"] == 0.0
    assert (tmp_path / "demos_learner1.npz").exists()
    assert (tmp_path / "visitation_ground_truth.png").exists()
    assert str(tmp_path) in out.stdout


@pytest.mark.parametrize("graph", group_options("graph"))
@pytest.mark.parametrize("logger", group_options("logger"))
def test_train_config_groups_instantiate(graph, logger, tmp_path):
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        cfg = compose(config_name="train", overrides=[f"graph={graph}", f"logger={logger}"])
    for n in (1, 3, 4):
        inner = build(cfg.graph.inner, n_learners=n)
        outer = build(cfg.graph.outer, n_learners=n)
        assert inner(0).shape == outer(0).shape == (n, n)
        assert build(cfg.comm, n_learners=n).n_learners == n
    steps = instantiate(cfg.algo.steps)
    assert 0 < steps.beta(0) < 1 and steps.alpha(0) > steps.alpha(1)
    kwargs = {"root": tmp_path} if "TensorBoard" in cfg.logger._target_ else {}
    instantiate(cfg.logger, **kwargs).close()


def test_train_runs_end_to_end(tmp_path):
    out = subprocess.run(
        [sys.executable, str(TRAIN), f"hydra.run.dir={tmp_path}",
         "env.layout.n_experts=1", "env.model.horizon=8", "solver.compile=false",
         "algo.outer_iterations=1", "algo.inner_steps=2", "eval_episodes=10",
         "n_demonstrations=10", "split=[4,6]"],
        capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    res = json.loads((tmp_path / "results.json").read_text())
    assert set(res["methods"]) == {"D-ICRL", "C-ICRL", "Experts (ground truth)",
                                   "Experts (nominal)"}
    assert len(res["methods"]["D-ICRL"]["learners"]) == 2
    for key in ("CR_mean", "CR_std", "FPR", "FNR", "CVR", "RFD", "SR"):
        assert key in res["methods"]["D-ICRL"]["learners"][0]
    assert (tmp_path / "tb" / "learner0").is_dir() and (tmp_path / "tb" / "network").is_dir()
    assert "FPR" in out.stdout and str(tmp_path) in out.stdout
    # every learner's run has the same outer/, inner/ and eval/ tags (docs/design.md §9)
    from tb_snapshot import read_scalars

    scalars = read_scalars(tmp_path)
    runs_of = {tag: set(runs) for tag, runs in scalars.items()}
    for prefix in ("outer/", "inner/", "eval/"):
        tags = [t for t in runs_of if t.startswith(prefix)]
        assert tags, prefix
        for tag in tags:
            assert {"learner0", "learner1"} <= runs_of[tag], tag
    for tag in ("consensus/max_pairwise_cost_distance", "consensus/max_pairwise_eta_distance"):
        assert runs_of[tag] == {"network"}, tag


def checkpointed_seconds(run_dir) -> list[float]:
    """The D-ICRL outer iterations' seconds kept in the run's checkpoint."""
    import torch

    saved = torch.load(run_dir / "checkpoint.pt", weights_only=True)
    return [h["seconds"] for h in saved["D-ICRL"]["history"]]


def test_kill_9_then_resume_reproduces_the_uninterrupted_run(tmp_path, tiny_reference):
    # a real process and a real SIGKILL (the other crash tests play it in-process)
    crashed = run_train(tmp_path / "crash", env={"DICRL_CRASH_AFTER": "D-ICRL:2"},
                        subprocess=True)
    assert crashed.returncode == -9  # killed mid-run, after outer iteration 2
    assert not (tmp_path / "crash" / "results.json").exists()
    before_kill = checkpointed_seconds(tmp_path / "crash")
    resumed = run_train(tmp_path / "crash", "resume=true")
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert "resuming from" in resumed.stdout
    assert comparable(tmp_path / "crash") == comparable(tiny_reference)
    # The training time counts the iterations run before the kill, as that process timed
    # them, besides the resumed process's own.
    seconds = checkpointed_seconds(tmp_path / "crash")
    assert len(before_kill) == 2 and seconds[:2] == before_kill and len(seconds) == 3
    results = json.loads((tmp_path / "crash" / "results.json").read_text())
    assert results["training_s"]["D-ICRL"] == pytest.approx(sum(seconds), rel=1e-12)
    assert set(results["training_s"]) == {"D-ICRL", "C-ICRL"}


@pytest.mark.slow  # ~15 s; resume in place is checked by the kill -9 test
def test_resume_elsewhere_restores_the_tensorboard_curves(tmp_path):
    """A checkpoint carried to a new run directory (another checkout or machine) arrives
    without its event files. The resumed run writes the checkpointed iterations' outer/
    and eval/ values, so its curves equal the uninterrupted run's."""
    import numpy as np
    from tb_snapshot import read_scalars

    logged = [o for o in TINY if not o.startswith("logger=")]

    def run_logged(run_dir, *extra, env=None):
        return train_here(run_dir, *logged, *extra,
                          crash_after=(env or {}).get("DICRL_CRASH_AFTER"))

    full = run_logged(tmp_path / "full")
    assert full.returncode == 0, full.stderr[-2000:]
    crashed = run_logged(tmp_path / "crash", env={"DICRL_CRASH_AFTER": "D-ICRL:2"})
    assert crashed.returncode == -9
    (tmp_path / "moved").mkdir()
    shutil.copy(tmp_path / "crash" / "checkpoint.pt", tmp_path / "moved")
    resumed = run_logged(tmp_path / "moved", "resume=true")
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    want, got = read_scalars(tmp_path / "full"), read_scalars(tmp_path / "moved")
    curves = [(tag, run) for tag in want if tag.startswith(("outer/", "eval/"))
              for run in want[tag]]
    assert ("eval/FNR", "learner1") in curves and ("outer/multiplier", "c_icrl") in curves
    for tag, run in curves:
        (want_steps, want_values), (got_steps, got_values) = want[tag][run], got[tag][run]
        assert list(got_steps) == list(want_steps), (tag, run)
        assert np.array_equal(got_values, want_values), (tag, run)


def test_same_seed_same_results(tmp_path, tiny_reference):
    a = run_train(tmp_path / "a")
    assert a.returncode == 0, a.stderr[-2000:]
    assert comparable(tmp_path / "a") == comparable(tiny_reference)


def test_own_shard_files_reproduce_the_sampled_run(tmp_path, tiny_reference):
    """A run on ``shard_files`` holding exactly the demonstrations a sampled run drew, split
    the same way, computes the same results.json (the config aside)."""
    from dicrl_torch.demos import (
        load_demonstrations,
        partition_demonstrations,
        save_demonstrations,
    )

    demos = load_demonstrations(tiny_reference / "demos.npz")
    files = [save_demonstrations(tmp_path / f"learner{v}.npz", shard)
             for v, shard in enumerate(partition_demonstrations(demos, [4, 6]))]
    own = run_train(tmp_path / "own", f"shard_files=[{files[0]},{files[1]}]")
    assert own.returncode == 0, own.stderr[-2000:]
    a, b = comparable(tiny_reference), comparable(tmp_path / "own")
    assert b["config"].pop("shard_files") == [str(f) for f in files]
    a["config"].pop("shard_files")
    assert a == b


# ------------------------------------------------- options that do not fit the environment
FITS_BOTH = {("baselines", "none")}
KIND_GROUPS = {"features/reward": "is a basis", "features/cost": "is a basis",
               "solver": "is a solver", "baselines": "are baselines"}
WORLDS = {"grid": "the grid world",
          "drones": "the continuous games (the drone arena, the MPE spread)"}


def world_of(group: str, option: str) -> str | None:
    if (group, option) in FITS_BOTH:
        return None
    text = (CONFIGS / group / f"{option}.yaml").read_text()
    return "drones" if any(m in text for m in DRONE_MARKERS) else "grid"


GAMES = {"drones": "the drone arena", "mpe_spread": "the MPE spread"}


def game_of(group: str, option: str) -> str | None:
    """The one continuous game an option is built for (None: any of its world's): an env
    option's own game; a basis's class ``game``."""
    text = (CONFIGS / group / f"{option}.yaml").read_text()
    if group == "env":
        return "mpe_spread" if "SpreadLayout" in text else "drones" if "arena:" in text else None
    if not group.startswith("features/"):
        return None
    from hydra.utils import get_class

    return getattr(get_class(OmegaConf.load(CONFIGS / group / f"{option}.yaml")["_target_"]),
                   "game", None)


def fits(env: str, group: str, option: str) -> bool:
    return world_of(group, option) == world_of("env", env) \
        and game_of(group, option) in (None, game_of("env", env))


def compose_for(env: str, *overrides: str):
    """``env`` with the experiment of its game (quick, table2_quick or mpe_quick)."""
    experiment = {"drones": "table2_quick", "mpe_spread": "mpe_quick"}.get(
        game_of("env", env), "quick")
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        return compose(config_name="train",
                       overrides=[f"experiment={experiment}", f"env={env}", *overrides])


def combinations(fit: bool) -> list[tuple[str, str, str]]:
    return [(env, group, option) for env in group_options("env") for group in KIND_GROUPS
            for option in group_options(group)
            if world_of(group, option) is not None and fits(env, group, option) == fit]


@pytest.mark.parametrize("env,group,option", combinations(fit=False))
def test_an_option_of_the_other_environment_is_refused(env, group, option):
    import common  # experiments/ is on pytest's pythonpath
    import config_checks

    with pytest.raises(config_checks.ConfigError) as info:
        common.check_config(compose_for(env, f"{group}={option}"))
    text = str(info.value)
    # one problem: the option's own keys are not checked against the wrong class or rules
    assert text.startswith("1 problem(s) in the configuration, nothing was computed:"), text
    if world_of(group, option) == world_of("env", env):  # the same world, another game
        theirs = GAMES[game_of(group, option)] + " only"
    else:
        theirs = WORLDS[world_of(group, option)]
    want = f"{group}={option} {KIND_GROUPS[group]} of {theirs}; with env={env} use {group}="
    assert want in text, text
    fix = text.split(want, 1)[1].split(" ", 1)[0].rstrip(".")
    assert fits(env, group, fix), text


@pytest.mark.parametrize("env,group,option", combinations(fit=True)
                         + [(env, "baselines", "none") for env in group_options("env")])
def test_an_option_of_the_environment_passes(env, group, option):
    import common  # experiments/ is on pytest's pythonpath

    common.check_config(compose_for(env, f"{group}={option}"))


def test_every_basis_says_which_environment_it_serves():
    from hydra.utils import get_class

    for group in ("features/reward", "features/cost"):
        for option in group_options(group):
            target = OmegaConf.load(CONFIGS / group / f"{option}.yaml")["_target_"]
            kind = get_class(target).env_kind
            assert kind == {"grid": "grid", "drones": "continuous"}[world_of(group, option)]


def test_the_cli_refuses_a_misfit_before_any_computation(tmp_path):
    out = train_here(tmp_path, "experiment=quick", "features/reward=fourier")
    assert out.returncode == 2, out.stderr[-3000:]
    assert ("features/reward=fourier is a basis of the continuous games (the drone arena, the MPE "
            "spread); with env=gridworld use "
            "features/reward=goal_closeness.") in out.stderr
    assert "Traceback" not in out.stderr
    assert {p.name for p in tmp_path.iterdir()} <= {".hydra", "train.log"}  # nothing else
