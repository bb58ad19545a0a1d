"""The constrained MPE spread as a run of the one runner (issue 27): the task builds, its
experts respect the true constraints, its identifiability counts add up, a tiny run goes
end to end through the runner (directly, and from the ``experiment=mpe_quick`` config),
and bad input is refused with the fix named (the README's "Your own environment" block:
tests/test_own_environment.py).

Tiny scale on one CPU thread: SAC steps in the tens; plumbing, not learning quality.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from dicrl_torch.algos.dicrl import StepSizes
from dicrl_torch.comm import SimulatedCommunicator
from dicrl_torch.comm.graphs import CompleteSchedule
from dicrl_torch.demos.continuous import (
    ContinuousDemonstrations,
    load_continuous_demonstrations,
    save_continuous_demonstrations,
)
from dicrl_torch.envs.mpe import (
    SUCCESS_RADIUS,
    in_disc,
    landmarks_covered,
    pairwise_too_close,
)
from dicrl_torch.features.continuous import ModuleBasis, PositionCellBasis, bounded_mlp
from dicrl_torch.features.mpe import LandmarkRewardBasis
from dicrl_torch.logger import NullLogger
from dicrl_torch.runs.mpe import MPETask, build_mpe_task, spread_success
from dicrl_torch.runs.runner import RunSettings, TrainerSpec, run_all_in_one

torch.set_num_threads(1)

ROOT = Path(__file__).resolve().parents[1]
MAX_STEPS = 30  # the via-point experts settle within 23 steps (2 agents)
# SAC at toy scale (as tests/test_generic_sac.py).
TINY_SOLVER = {"learning_starts": 30, "batch_size": 16, "net_arch": [16, 16], "n_envs": 2,
               "buffer_size": 2000}
TINY = dict(env={"max_steps": MAX_STEPS}, solver=TINY_SOLVER, eval_episodes=3,
            timesteps=30, n_eval_episodes=2, warmup_timesteps=60)


def tiny_task(**kwargs) -> MPETask:
    return build_mpe_task(**{**TINY, "split": [2, 3], "seed": 0, **kwargs})


@pytest.fixture(scope="module")
def task() -> MPETask:
    return tiny_task()


def trainer_spec(task: MPETask) -> TrainerSpec:
    return TrainerSpec(
        schedules=lambda n: (CompleteSchedule(n_learners=n), CompleteSchedule(n_learners=n)),
        steps=StepSizes(alpha_bar=0.002), inner_step=0.005, n_shards=len(task.split),
        options=dict(inner_steps=2, lsca_curvature=50.0, prune_accrued=True))


def run_tiny(task: MPETask, out: Path) -> dict:
    settings = RunSettings(experiment="mpe_tiny", config={}, training_config={"run": "tiny"},
                           outer_iterations=1)
    return run_all_in_one(task, settings, trainer_spec(task), out=out,
                          t_start=time.perf_counter(), logger=NullLogger(),
                          communicator=lambda n: SimulatedCommunicator(n_learners=n))


# ------------------------------------------------------------------ the task
def test_the_task_builds_with_its_shards_bases_and_truth(task):
    assert task.split == [2, 3] and [s.n_episodes for s in task.shards] == [2, 3]
    assert task.demos.n_episodes == 5 and task.demos.states.shape[2:] == (2, 4)
    assert task.reward_basis.dim == 2 and task.cost_basis.dim == 8 * 8 + 1
    # 8 x 8 cells over [-1.5, 1.5]²: grid lines through the disc's centre, so the 4 cells
    # around it overlap the disc; the proximity feature is the distance constraint.
    names = [task.cost_basis.names[j] for j in np.flatnonzero(task.true)]
    assert names == ["cell(3,3)", "cell(4,3)", "cell(3,4)", "cell(4,4)", "proximity"]
    assert task.columns == ("FPR", "FNR", "FNR_required", "region_recall",
                            "region_precision", "region_precision_determined", "region_iou",
                            "CVR", "SR")
    assert "2 learners holding [2, 3]" in task.describe()


def test_the_demonstrations_respect_the_true_constraints(task):
    """Checked from the recorded states themselves, not by the env's verdict the task
    used to keep them: no agent ever in the disc, never two closer than min_distance
    (CVR 0), every landmark covered by a distinct agent at the end (success 1)."""
    lay, d = task.layout, task.demos
    final = np.stack([d.states[k, int(n), :, :2] for k, n in enumerate(d.lengths)])
    violated = np.zeros((d.n_episodes, lay.n_agents), dtype=bool)
    for k, n in enumerate(d.lengths):
        pos = d.states[k, 1:int(n) + 1, :, :2]  # [L, N, 2]: the states after each step
        violated[k] = (in_disc(pos, lay.disc_centre, lay.disc_radius)
                       | pairwise_too_close(pos, lay.min_distance)).any(0)
    assert not violated.any()  # CVR 0
    assert spread_success(final, violated, lay).all()  # SR 1
    assert all(landmarks_covered(p, lay.landmark_array, SUCCESS_RADIUS) for p in final)
    rows = task.reference_rows()
    assert (rows["Experts (ground truth)"]["SR"], rows["Experts (ground truth)"]["CVR"]) \
        == (1.0, 0.0)
    # Straight to the landmarks crosses the disc and converges: the nominal controller
    # violates in the true game.
    assert rows["Experts (nominal)"]["CVR"] > 0.5 and rows["Experts (nominal)"]["SR"] == 0.0


def test_a_solvers_reached_agents_give_the_spreads_task_success(task):
    """The solver's per-agent ``reached`` (the env's last-step covering) is the task's
    success, as the table computes it from the final positions: every agent reached and
    none violated exactly when :func:`spread_success`; success under the TRUE set
    (with no agent violating anything else) is the mean of that."""
    solver = task.base.clone(5)
    for true_game in (False, True):
        ev = solver.evaluate(16, deterministic=False, true_game=true_game,
                             trajectories=True, rng=np.random.default_rng(1))
        final = np.stack([p[-1, :, :2] for p in ev.paths])
        violated = ev.violated.numpy()
        per_episode = ev.reached.numpy().all(1) & ~violated.any(1)
        np.testing.assert_array_equal(per_episode,
                                      spread_success(final, violated, task.layout))
    # Agents placed on the landmarks (one per landmark) reach them at the last step.
    env = task._true_env
    env.reset(seed=0, options={"positions": task.layout.landmark_array})
    for _ in range(env.max_steps):
        _, _, _, _, infos = env.step({a: np.zeros(2) for a in env.agents})
    assert all(v["reached"] for v in infos.values())


def test_identifiability_counts_are_consistent(task):
    ident = task.identifiability()
    true = torch.from_numpy(task.true)
    classes = [ident.demonstrated, ident.required, ident.undetermined]
    assert torch.equal(classes[0] | classes[1] | classes[2], true)  # they cover the truth
    assert not (classes[0] & classes[1]).any() and not (classes[1] & classes[2]).any() \
        and not (classes[0] & classes[2]).any()  # and partition it
    assert ident.n_demonstrated + ident.n_required + ident.n_undetermined == int(true.sum())
    # The experts avoid every true constraint that the nominal controller uses.
    assert ident.n_demonstrated == 0 and ident.n_required == 5
    record = ident.as_dict()
    assert record["n_required"] == len(record["required"]) == 5
    # The learned rows are annotated: FNR_required counts the misses among the required.
    names = list(task.cost_basis.names)
    rows = {"A": {"learners": [{"constraints": [names[j] for j in np.flatnonzero(task.true)]},
                               {"constraints": []}, {"constraints": ["cell(1,3)"]}]},
            "Experts (ground truth)": {"learners": [{"SR": 1.0}]}}
    out = task.annotate(rows)
    assert out["n_required"] == 5 and "seconds" in out
    first, empty, start = rows["A"]["learners"]
    assert first["FNR_required"] == 0.0 and empty["FNR_required"] == 1.0
    # A cell of the start region is accrued (the demonstrations start there): learning
    # it as a constraint contradicts the data.
    assert start["contradictions"] == ["cell(1,3)"] and first["contradictions"] == []
    assert "FNR_required" not in rows["Experts (ground truth)"]["learners"][0]


def test_finer_cells_leave_a_true_constraint_undetermined():
    """16 x 16 cells: 17 true constraints (16 cells under the disc and the proximity);
    the classes still add up."""
    cost = PositionCellBasis(n_agents=2, bounds=((-1.5, 1.5), (-1.5, 1.5)), n_per_axis=16,
                             proximity_radius=0.4, state_dim=4)
    t = tiny_task(cost_basis=cost, split=[6, 6], warmup_timesteps=0)
    ident = t.identifiability()
    assert int(t.true.sum()) == 17
    assert ident.n_demonstrated + ident.n_required + ident.n_undetermined == 17
    assert ident.n_required >= 1


# ------------------------------------------------------------------ end to end
def test_a_tiny_run_goes_through_the_runner(task, tmp_path):
    """D-ICRL, C-ICRL, M(C)E-greedy (given D-ICRL's reward) and the reference rows."""
    task = tiny_task(demos=task.demos, baseline=True, baseline_timesteps=20,
                     baseline_max_constraints=1)
    res = run_tiny(task, tmp_path)
    methods = res["methods"]
    assert list(methods) == ["D-ICRL", "C-ICRL", "M(C)E-greedy", "Experts (ground truth)",
                             "Experts (nominal)"]
    for name in ("D-ICRL", "C-ICRL", "M(C)E-greedy"):
        for row in methods[name]["learners"]:
            assert 0 <= row["SR"] <= 1 and 0 <= row["CVR"] <= 1
            assert (row["SR"], row["CVR"]) == (row["SR_mean"], row["CVR_mean"])
            assert 0 <= row["FPR"] <= 1 and 0 <= row["FNR"] <= 1
            assert row["n_required"] == 5 and row["FNR_required"] is not None
    assert len(res["history"]["M(C)E-greedy"]) >= 1
    assert res["identifiability"]["n_required"] == 5
    saved = json.loads((tmp_path / "results.json").read_text())
    assert saved["identifiability"] == res["identifiability"]
    for png in ("spread_demonstrations", "constraints_D-ICRL_1", "constraints_D-ICRL_2",
                "constraints_C-ICRL_1", "constraints_MCE-greedy", "cost_weights"):
        assert (tmp_path / f"{png}.png").stat().st_size > 0
    demos = load_continuous_demonstrations(tmp_path / "demos.npz")
    assert demos == task.demos


CONFIG_TINY = ["env.arena.max_steps=30", "eval_episodes=2", "n_demonstrations=4",
               "split=[2,2]", "solver.warmup_timesteps=40", "solver.timesteps=20",
               "solver.final_timesteps=20", "solver.final_checks=2",
               "solver.n_eval_episodes=1", "solver.solver.learning_starts=20",
               "solver.solver.batch_size=16", "solver.solver.net_arch=[16,16]",
               "solver.solver.n_envs=2", "algo.outer_iterations=1", "algo.inner_steps=2",
               "logger=none"]


# position_cells is mpe_quick's own basis, run end to end by tests/test_sac_runs.py
@pytest.mark.parametrize("cost", [pytest.param("features/cost=position_cells",
                                               marks=pytest.mark.slow),
                                  "features/cost=local_relu"])
def test_the_mpe_quick_config_runs_end_to_end(cost, tmp_path):
    """``experiment=mpe_quick`` (``env=mpe_spread``, ``features/reward=landmark_coverage``)
    checked, built by experiments/common.py's dispatch and run through the runner as
    ``experiments/train.py`` runs a simulated job, with either cost basis."""
    from common import (  # experiments/ on the path
        build,
        check_config,
        mpe_task,
        run_settings,
        trainer_spec,
    )
    from tiny_train import compose_train

    cfg = compose_train("experiment=mpe_quick", "env=mpe_spread",
                        "features/reward=landmark_coverage", cost, "comm=simulated",
                        *CONFIG_TINY)
    check_config(cfg)  # every key known, every value in range
    t = mpe_task(cfg)
    assert isinstance(t, MPETask) and t.split == [2, 2]
    assert not t.base.absorbing and t.base.ent_coef == 0.1
    cells = cost.endswith("position_cells")
    res = run_all_in_one(t, run_settings(cfg), trainer_spec(cfg), out=tmp_path,
                         t_start=time.perf_counter(), logger=NullLogger(),
                         communicator=lambda n: build(cfg.comm, n_learners=n))
    rows = [r for m in ("D-ICRL", "C-ICRL") for r in res["methods"][m]["learners"]]
    assert len(rows) == 3 and all(0 <= r["CVR"] <= 1 and 0 <= r["SR"] <= 1 for r in rows)
    # the last solve's chunks were ranked by success under each learner's own set
    assert all(len(r["final_checks"]) == 2 for r in rows)
    assert all(0 <= c["success_under_constraints"] <= 1
               for r in rows for c in r["final_checks"])
    if cells:
        assert int(t.true.sum()) == 5 and res["identifiability"]["n_required"] == 5
        assert all(0 <= r["FPR"] <= 1 for r in rows)
    else:  # local units have no per-feature truth: FPR, FNR and the classes are null
        assert t.true is None and t.cost_basis.dim == 144 + 24
        assert res["identifiability"] is None
        assert all(r["FPR"] is None and r["FNR_required"] is None for r in rows)
    # every basis's learned set scored as a region, with the bound said before training
    for r in rows:
        assert 0 <= r["region_recall"] <= r["region_recall_bound"] + 1e-12 <= 1 + 1e-12
        assert 0 <= r["region_precision"] <= r["region_precision_determined"] <= 1
    assert (tmp_path / "region_D-ICRL_1.png").stat().st_size > 0
    # the study that scores finished runs rebuilds the same test set from the config
    from studies.region_scores import scores

    again = {(r["method"], r["learner"]): r for r in scores(tmp_path)}
    for name in ("D-ICRL", "C-ICRL"):
        for v, row in enumerate(res["methods"][name]["learners"]):
            for key in ("region_recall", "region_precision", "region_recall_bound"):
                assert again[(name, v + 1)][key] == row[key], (name, v, key)


def test_a_cost_basis_that_can_express_nothing_is_refused_before_training(tmp_path):
    """A network ending in a sigmoid is positive everywhere: every feature is positive on
    every demonstration, so with budget 0 none can be a constraint. The run is refused
    at its start, the message naming the cause and the fix; the sigmoid's positive
    outputs are why the bound of what it can express is 0."""
    sigmoid = ModuleBasis(module=bounded_mlp(8, 6, hidden=(16,), seed=0), dim=6,
                          n_agents=2, state_dim=4)
    t = tiny_task(cost_basis=sigmoid)
    assert not t.constrainable().any()
    assert t.expressivity() == [0.0, 0.0, 0.0]
    with pytest.raises(ValueError, match=r"can express no constraint.*sigmoid.*"
                                         r"features/cost=local_relu"):
        run_tiny(t, tmp_path)
    assert not (tmp_path / "results.json").exists()
    cells = tiny_task()
    assert cells.constrainable().any(1).all()  # the disc cells: no expert enters them
    assert cells.expressivity() == [1.0, 1.0, 1.0]


def test_the_shipped_mpe_quick_config_composes_unchanged():
    from common import check_config
    from tiny_train import compose_train

    cfg = compose_train("experiment=mpe_quick")
    check_config(cfg)
    assert cfg.name == "mpe_quick" and list(cfg.split) == [10, 10]
    assert cfg.solver.solver.absorbing is False
    assert cfg.solver.solver.split_cost_critic and cfg.solver.solver.per_agent_critics
    assert cfg.env.expert.lane_spread == 0.5  # the experts vary their lanes
    assert cfg.env.expert.exit_spread == 0.2  # and where they leave them
    # the first LSCA step clips every feature the warm-up policy enters (docs/mpe.md)
    assert cfg.algo.init_multiplier == -5.0 and cfg.algo.lsca_curvature == 10.0
    assert cfg.algo.steps.beta_power == 0.65 and cfg.solver.n_eval_episodes == 40
    assert cfg.solver.final_score == "learned_success"
    # learner processes, C-ICRL beside them (the numbers are the one-process run's)
    assert cfg.comm._target_.endswith("DistributedCommunicator")
    assert cfg.algo.c_icrl_beside_learners is True
    from common import mpe_task  # the expert node reaches the controller
    tiny = compose_train("experiment=mpe_quick", *CONFIG_TINY)
    assert mpe_task(tiny).expert_kwargs == {"lane_spread": 0.5, "exit_spread": 0.2}
    from config_checks import ConfigError
    with pytest.raises(ConfigError, match="did you mean 'lane_spread'"):
        check_config(compose_train("experiment=mpe_quick", "+env.expert.lane_sprad=0.3"))


# ------------------------------------------------------------------ bad input
def demos_like(task: MPETask, **change) -> ContinuousDemonstrations:
    d = task.demos
    fields = dict(states=np.array(d.states), actions=np.array(d.actions),
                  lengths=np.array(d.lengths))
    fields.update(change)
    return ContinuousDemonstrations(**fields)


def test_demonstrations_that_do_not_fit_the_env_are_refused(task, tmp_path):
    d = task.demos
    with pytest.raises(ValueError, match=r"'states' has per-step shape \[2, 3\].*\[2, 4\]"):
        tiny_task(demos=demos_like(task, states=np.array(d.states)[..., :3]))
    three = np.concatenate([d.states, d.states[:, :, :1]], 2)
    with pytest.raises(ValueError, match=r"'states' has per-step shape \[3, 4\]"):
        tiny_task(demos=demos_like(task, states=three,
                                   actions=np.concatenate([d.actions, d.actions[:, :, :1]],
                                                          2)))
    with pytest.raises(ValueError, match="'actions'.*joint action has 4"):
        tiny_task(demos=demos_like(task, actions=np.concatenate([d.actions, d.actions], -1)))
    wild = np.array(d.actions)
    wild[0, 0, 0, 0] = 3.0
    with pytest.raises(ValueError, match=r"outside the env's action box.*np.clip"):
        tiny_task(demos=demos_like(task, actions=wild))
    with pytest.raises(ValueError, match="split .* sums to 5, but there are 4"):
        tiny_task(demos=d.subset(range(4)))
    # A file is read with the env's dimensions: one for another game is refused by name.
    path = save_continuous_demonstrations(tmp_path / "other.npz",
                                          demos_like(task, states=np.array(d.states)[..., :3]))
    with pytest.raises(ValueError, match="other.npz"):
        tiny_task(demos=path)


def test_a_cost_basis_out_of_range_or_of_the_wrong_width_is_refused(task):
    linear = nn.Linear(8, 4)
    with torch.no_grad():  # negative outputs: not bounded features
        linear.weight.fill_(-1.0)
        linear.bias.fill_(-1.0)
    with pytest.raises(ValueError, match=r"cost_basis.*leave \[0, 1.0\].*ScaledSigmoid"):
        tiny_task(demos=task.demos, cost_basis=ModuleBasis(module=linear, dim=4))
    wide = ModuleBasis(module=bounded_mlp(8, 5, seed=0), dim=4)
    with pytest.raises(ValueError, match="cost_basis.*returns 5 features per sample but "
                                         "dim = 4"):
        tiny_task(demos=task.demos, cost_basis=wide)

    class Loud(nn.Module):  # not a checked basis: the task checks it itself
        dim, max_value, names = 3, 1.0, ["a", "b", "c"]

        def forward(self, states):
            return torch.full((*states.shape[:-2], 3), 2.0, dtype=states.dtype)

    with pytest.raises(ValueError, match=r"cost_basis Loud returned values in \[2, 2\], "
                                         r"outside \[0, max_value=1.0\]"):
        tiny_task(demos=task.demos, cost_basis=Loud())
    cells = PositionCellBasis(n_agents=2, bounds=((0, 10), (0, 10)), proximity_radius=0.4)
    with pytest.raises(ValueError, match=r"walls are at ±1.5"):
        tiny_task(demos=task.demos, cost_basis=cells)


def test_a_basis_built_for_the_drone_arena_is_refused(task):
    """The drone bases share the spread's state shape ([2, 4]) but not its geometry: a
    silent wrong answer unless refused."""
    from dicrl_torch.features.drone import CellOccupancyCostBasis, DoorLocationRewardBasis

    with pytest.raises(ValueError, match=r"cost basis CellOccupancyCostBasis is built on "
                                         r"the geometry of the game 'drones', not of "
                                         r"'mpe_spread'.*PositionCellBasis"):
        tiny_task(demos=task.demos, cost_basis=CellOccupancyCostBasis())
    with pytest.raises(ValueError, match="reward basis DoorLocationRewardBasis .* 'drones'"):
        tiny_task(demos=task.demos, reward_basis=DoorLocationRewardBasis())


def test_settings_the_spread_cannot_honour_are_refused(task):
    with pytest.raises(ValueError, match="absorbing=False"):
        tiny_task(demos=task.demos, solver={**TINY_SOLVER, "absorbing": True})
    with pytest.raises(ValueError, match="landmarks=layout.landmarks"):
        tiny_task(demos=task.demos,
                  reward_basis=LandmarkRewardBasis(n_agents=2, landmarks=[[0, 1], [1, 1]]))
    with pytest.raises(ValueError, match="eval_action"):
        tiny_task(demos=task.demos, eval_action="greedy")
    with pytest.raises(RuntimeError, match="give the experts time"):
        tiny_task(env={"max_steps": 10})


def test_a_rows_map_draws_its_own_rollouts_whatever_was_evaluated_since(task):
    """The evaluation hands its rollouts back with the row and keeps none: a row's map
    drawn after another evaluation is the one drawn right after its own; one drawn
    without rollouts (a row from a checkpoint) shows none, not the last evaluation's."""
    solver = task.base.clone(11)
    _, _, mean = task.evaluate_policy(solver, deterministic=True)
    assert len(mean) == task.eval_episodes and mean[0].shape[1:] == (2, 2)
    row = {"constraints": ["cell(3,3)", "proximity"]}
    first = task.constraint_map("learner 1", row, mean)
    _, _, sampled = task.evaluate_policy(solver, deterministic=False)  # another row's
    assert not all(np.array_equal(a, b) for a, b in zip(mean, sampled, strict=True))
    np.testing.assert_array_equal(task.constraint_map("learner 1", row, mean), first)
    assert not np.array_equal(task.constraint_map("learner 1", row, sampled), first)
    assert not np.array_equal(task.constraint_map("learner 1", row), first)


# ------------------------------------------------------------------ the reward basis
def test_landmark_reward_basis_shapes_values_and_shares():
    basis = LandmarkRewardBasis(n_agents=2, landmarks=((0.5, 0.0), (1.0, 0.0)),
                                features=["closeness", "coverage"], sigma=0.5)
    assert basis.names == ["landmark0", "landmark1", "agent0/landmark0", "agent0/landmark1",
                           "agent1/landmark0", "agent1/landmark1"]
    states = torch.zeros(3, 5, 2, 4, dtype=torch.float64)  # [..., N, d_s]
    states[..., 0, :2] = torch.tensor([0.5, 0.0])  # agent 0 on landmark 0
    states[..., 1, :2] = torch.tensor([0.5, 1.0])  # agent 1 one unit off landmark 0
    phi = basis(states)
    assert phi.shape == (3, 5, 6) and phi.dtype == torch.float64
    d11 = float(np.hypot(0.5, 1.0))
    want = torch.tensor([1.0, np.exp(-0.5 / 0.5), 1.0, np.exp(-0.5 / 0.5), np.exp(-1 / 0.5),
                         np.exp(-d11 / 0.5)], dtype=torch.float64)
    torch.testing.assert_close(phi[0, 0], want)
    shares = basis.agent_shares()
    assert shares.shape == (6, 2)
    torch.testing.assert_close(shares.sum(1), torch.ones(6, dtype=torch.float64))
    assert shares[0].tolist() == [0.5, 0.5] and shares[3].tolist() == [1.0, 0.0] \
        and shares[4].tolist() == [0.0, 1.0]
    with pytest.raises(ValueError, match="features must be distinct names"):
        LandmarkRewardBasis(n_agents=2, features=["coverage", "goal"])
    with pytest.raises(ValueError, match="sigma must be a positive length"):
        LandmarkRewardBasis(n_agents=2, sigma=0.0)


# ------------------------------------------------------------------ the targets
@pytest.mark.slow  # ~2 min alone on 2 cores (D-ICRL only)
@pytest.mark.timeout(1800)
@pytest.mark.xfail(strict=True, reason=(
    "the lean loop's seed 0: the warm-up's policy enters three free corner cells, whose "
    "first LSCA step lands them at omega_c 0.50, and (3,3) ends at 0.45 (FPR 0.43, FNR "
    "0.20; docs/mpe.md). SB3's loop met the targets at seed 0 on the machine that "
    "committed it, not on another (docs/mpe_runs/sb3)."))
def test_mpe_quick_meets_the_targets_at_seed_0(tmp_path):
    """``experiment=mpe_quick`` as shipped, D-ICRL only (C-ICRL off: its own last solve
    is half the run): every D-learner finds the true set (FPR, FNR ≤ 0.10), keeps to it
    (CVR ≤ 0.05) and succeeds at ≥ 0.9 × the experts' rate (issue 27's targets).
    Of the committed lean runs (docs/mpe.md) seeds 1, 3 and 4 meet them, 0 and 2 do not."""
    out = subprocess.run([sys.executable, str(ROOT / "experiments" / "train.py"),
                          f"hydra.run.dir={tmp_path}", "experiment=mpe_quick", "seed=0",
                          "algo.run_c_icrl=false", "logger=none"],
                         capture_output=True, text=True, cwd=ROOT, timeout=1700)
    assert out.returncode == 0, out.stderr[-3000:]
    res = json.loads((tmp_path / "results.json").read_text())
    experts = res["methods"]["Experts (ground truth)"]["learners"][0]["SR"]
    assert experts == 1.0
    rows = res["methods"]["D-ICRL"]["learners"]
    assert len(rows) == 2
    for row in rows:
        assert row["FPR"] <= 0.10 and row["FNR"] <= 0.10, row["constraints"]
        assert row["CVR"] <= 0.05 and row["SR"] >= 0.9 * experts, (row["CVR"], row["SR"])


def test_planning_needs_a_game_with_a_model():
    """eval_policy='plan' plans in the task's model of its nominal game; the spread's task
    gives none, and says so when built."""
    with pytest.raises(ValueError, match="needs a model of the nominal game"):
        tiny_task(eval_policy="plan")
    with pytest.raises(ValueError, match="eval_policy='search' is invalid"):
        tiny_task(eval_policy="search")


def test_warmup_keeps_the_best_scored_chunk_of_several_lineages(capsys):
    """warmup_restarts / warmup_checks: the warm-up scores every chunk of every lineage by
    the nominal share of agents at their goals (no constraint known) and keeps the best;
    1 and 1 is the plain warm-up. Bad values are refused, naming the setting."""
    t = tiny_task(warmup_restarts=2, warmup_checks=2)
    base = t._warmed_base()
    checks = base.last_checks
    assert [(c["restart"], c["timesteps"]) for c in checks] == [(0, 30), (0, 60), (1, 30),
                                                                (1, 60)]
    assert all(0.0 <= c["success_under_constraints"] <= 1.0 for c in checks)
    assert "SAC warm-up: 60 steps" in capsys.readouterr().out
    plain = tiny_task()
    plain._warmed_base()
    assert plain.base.last_checks == []  # one lineage, one chunk: solve, no scoring
    with pytest.raises(ValueError, match="warmup_restarts"):
        tiny_task(warmup_restarts=0)
    with pytest.raises(ValueError, match=r"warmup_until_success=1.0 is invalid.*"
                                         r"warmup_checks=1"):
        tiny_task(warmup_until_success=1.0)
    with pytest.raises(ValueError, match=r"warmup_until_success=0 is invalid.*\(0, 1\]"):
        tiny_task(warmup_checks=2, warmup_until_success=0)
    with pytest.raises(ValueError, match=r"warmup_checks=100 is invalid.*warmup_timesteps=60\]"):
        tiny_task(warmup_checks=100)


def test_the_warm_up_is_kept_in_the_run_directory(tmp_path, capsys):
    """bind_run_dir: the first task trains the warm-up and saves it; another task of the
    same config loads it into exactly the trained state; another config, or an unreadable
    file, trains it again (the message names the file)."""
    from test_sac_state import assert_same_solution, assert_same_solver

    config = {"seed": 0, "solver.warmup_timesteps": 60}
    first = tiny_task()
    first.bind_run_dir(tmp_path, config)
    trained = first._warmed_base()
    assert (tmp_path / "warmup.pt").is_file()
    again = tiny_task()
    again.bind_run_dir(tmp_path, config)
    loaded = again._warmed_base()
    assert "SAC warm-up loaded from" in capsys.readouterr().out
    assert_same_solver(loaded, trained)
    eta, cw = first.eta0.numpy(), first.cw0.numpy()
    assert_same_solution(loaded.solve(eta, cw, 20), trained.solve(eta, cw, 20))

    other = tiny_task()
    other.bind_run_dir(tmp_path, {**config, "seed": 1})
    other._warmed_base()
    assert "SAC warm-up: 60 steps" in capsys.readouterr().out
    (tmp_path / "warmup.pt").write_bytes(b"not a torch file")
    broken = tiny_task()
    broken.bind_run_dir(tmp_path, config)
    broken._warmed_base()
    out = capsys.readouterr().out
    assert "warmup.pt is unreadable" in out and "SAC warm-up: 60 steps" in out


def test_learner_processes_share_the_warm_up_lineages(tmp_path, capsys, monkeypatch):
    """bind_run_dir(process=p, processes=2) with 3 lineages: process 1 trains lineage 1
    and leaves it in warmup_lineages/ (then waits for warmup.pt: here a short wait that
    times out, naming the fix); process 0 trains lineages 0 and 2, adopts the best of the
    three and writes warmup.pt, which equals the one-process warm-up; process 1 of a new
    start loads it."""
    from test_sac_state import assert_same_solution, assert_same_solver

    from dicrl_torch.runs import continuous

    # Seed 7: the best chunk is lineage 1's (1.89 against 1.76), the lineage another
    # process trains, so the test shows that its file is read and adopted.
    config = {"seed": 7, "solver.warmup_timesteps": 60, "restarts": 3}
    settings = dict(warmup_restarts=3, warmup_checks=2, seed=7)
    alone = tiny_task(**settings)
    alone.bind_run_dir(tmp_path / "alone", config)
    whole = alone._warmed_base()

    monkeypatch.setattr(continuous, "WARMUP_WAIT_S", 0.5)
    second = tiny_task(**settings)
    second.bind_run_dir(tmp_path, config, process=1, processes=2)
    with pytest.raises(TimeoutError, match="was not written .* by learner process 0.*"
                                           "shared file system"):
        second._warmed_base()
    assert sorted(q.name for q in (tmp_path / "warmup_lineages").iterdir()) == ["lineage1.pt"]
    first = tiny_task(**settings)
    first.bind_run_dir(tmp_path, config, process=0, processes=2)
    shared = first._warmed_base()
    assert "waiting for lineages [1]" in capsys.readouterr().out
    assert not (tmp_path / "warmup_lineages").exists()  # removed once warmup.pt is written
    assert shared.last_checks == whole.last_checks
    best = max(whole.last_checks, key=lambda c: (c["success_under_constraints"],
                                                  c["penalised_return"], -c["restart"]))
    assert best["restart"] == 1  # (this seed) the other process's lineage is adopted
    assert_same_solver(shared, whole)
    again = tiny_task(**settings)
    again.bind_run_dir(tmp_path, config, process=1, processes=2)
    assert_same_solver(again._warmed_base(), whole)
    assert "SAC warm-up loaded from" in capsys.readouterr().out
    eta, cw = first.eta0.numpy(), first.cw0.numpy()
    assert_same_solution(again.base.solve(eta, cw, 20), whole.solve(eta, cw, 20))
    with pytest.raises(ValueError, match=r"process must lie in \[0, processes\)"):
        tiny_task().bind_run_dir(tmp_path, config, process=2, processes=2)


def test_a_plain_warm_up_is_trained_by_process_0_alone(tmp_path, monkeypatch):
    """One lineage, one chunk, shared by 2 processes: process 1 trains nothing and waits
    for warmup.pt (here a short wait that times out); process 0 trains it; process 1 of
    a new start loads exactly that."""
    from test_sac_state import assert_same_solver

    from dicrl_torch.runs import continuous

    config = {"seed": 0, "solver.warmup_timesteps": 60}
    monkeypatch.setattr(continuous, "WARMUP_WAIT_S", 0.5)
    second = tiny_task()
    second.bind_run_dir(tmp_path, config, process=1, processes=2)
    with pytest.raises(TimeoutError, match="by learner process 0"):
        second._warmed_base()
    assert second.base.num_timesteps == 0  # it waited, it did not train
    first = tiny_task()
    first.bind_run_dir(tmp_path, config, process=0, processes=2)
    trained = first._warmed_base()
    assert trained.num_timesteps == 60
    again = tiny_task()
    again.bind_run_dir(tmp_path, config, process=1, processes=2)
    assert_same_solver(again._warmed_base(), trained)


@pytest.mark.slow  # ~12 s; the shared warm-up is checked by the learner-process test
def test_a_waiting_process_reads_another_configs_warm_up_once(tmp_path, monkeypatch):
    """A reused run directory holds warmup.pt and a lineage file of another config:
    while waiting, a process loads each once (not once a second), and it loads a
    replacement of this config as soon as it appears."""
    from dicrl_torch.runs import continuous
    from dicrl_torch.runs.continuous import WARMUP_FILE, WARMUP_LINEAGES_DIR

    config = {"seed": 0, "solver.warmup_timesteps": 60}
    stale = {"key": "another config", "summary": "x", "solver": {}, "lineage": {}}
    torch.save(stale, tmp_path / WARMUP_FILE)
    (tmp_path / WARMUP_LINEAGES_DIR).mkdir()
    torch.save(stale, tmp_path / WARMUP_LINEAGES_DIR / "lineage1.pt")
    loads = []
    real_load = torch.load

    def counting_load(path, *args, **kwargs):
        loads.append(Path(path).name)
        return real_load(path, *args, **kwargs)

    monkeypatch.setattr(continuous.torch, "load", counting_load)
    monkeypatch.setattr(continuous, "WARMUP_WAIT_S", 3.5)
    waiting = tiny_task()
    waiting.bind_run_dir(tmp_path, config, process=1, processes=2)
    with pytest.raises(TimeoutError, match="by learner process 0"):
        waiting._warmed_base()
    assert loads == [WARMUP_FILE]  # ~4 one-second polls, one read
    loads.clear()
    adopting = tiny_task(warmup_restarts=2, warmup_checks=1)
    adopting.bind_run_dir(tmp_path, config, process=0, processes=2)
    with pytest.raises(TimeoutError, match="lineages \\[1\\] did not appear"):
        adopting._warmed_base()
    assert loads.count("lineage1.pt") == 1
    # process 0 writes this config's warm-up over the stale file: loaded at once
    trained = tiny_task()
    trained.bind_run_dir(tmp_path, config, process=0, processes=1)
    trained._warmed_base()
    again = tiny_task()
    again.bind_run_dir(tmp_path, config, process=1, processes=2)
    assert again._warmed_base().num_timesteps == 60
