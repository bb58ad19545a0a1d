"""The same D-ICRL trainer on the drone arena: SACLearnerModel, solver clones, the
M(C)E-greedy baseline and the Table 2 entry point (experiment=table2_quick)."""

from __future__ import annotations

import functools
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from tiny_train import TRAIN, train_cli

from dicrl_torch.algos.dicrl import DICRL, StepSizes
from dicrl_torch.algos.greedy import SACGreedyConstraintInference
from dicrl_torch.algos.models import LearnerModel, SACLearnerModel
from dicrl_torch.comm import ALLOWED_FIELDS, CompleteSchedule, SimulatedCommunicator
from dicrl_torch.demos import partition_demonstrations
from dicrl_torch.demos.drone_demos import make_drone_demonstrations
from dicrl_torch.envs.drones import JointDroneEnv, in_obstacle, start_support
from dicrl_torch.features.drone import CellOccupancyCostBasis, DoorLocationRewardBasis
from dicrl_torch.solvers.drone_planning import PLANNER_DEFAULTS
from dicrl_torch.solvers.sac import SACConstrainedSolver, discounted_demo_feature_sums

ROOT = Path(__file__).resolve().parents[1]
GAMMA = 0.95


def make_solver(seed: int = 0, engine: str = "lean") -> SACConstrainedSolver:
    return SACConstrainedSolver(
        reward_basis=DoorLocationRewardBasis(), cost_basis=CellOccupancyCostBasis(), seed=seed,
        n_envs=2, gamma=GAMMA, learning_starts=40, batch_size=16, net_arch=(16, 16),
        env_factory=functools.partial(JointDroneEnv, max_steps=20), n_eval_episodes=2,
        engine=engine)


@pytest.fixture(scope="module")
def demos():
    return make_drone_demonstrations(3, rng=np.random.default_rng(0))


class Recorder(SimulatedCommunicator):
    """The audit log's fields: every message the learners sent."""

    def __init__(self, n):
        super().__init__(n, record=True)

    @property
    def fields(self) -> set[str]:
        return {m.field for m in self.messages}


def trainer(demos, seed: int, communicator=None) -> DICRL:
    base = make_solver(seed)
    shards = partition_demonstrations(demos, [1, 2])
    model = SACLearnerModel(solvers=[base.clone(seed + 10), base.clone(seed + 11)],
                            timesteps=30, n_eval_episodes=2, start_states=start_support())
    return DICRL(learner_model=model, shards=shards, trajectory_counts=[1, 2],
                 communicator=communicator or SimulatedCommunicator(2),
                 inner_schedule=CompleteSchedule(n_learners=2),
                 outer_schedule=CompleteSchedule(n_learners=2),
                 steps=StepSizes(alpha_bar=0.01), inner_steps=2, lsca_curvature=20.0,
                 prune_accrued=True, init_cost_weights=0.0, init_reward_weights=1.0)


def test_learner_model_statistics_are_the_demonstrations_feature_sums(demos):
    model = SACLearnerModel(solvers=[make_solver()], timesteps=10)
    assert isinstance(model, LearnerModel) and model.stateful
    st = model.statistics(demos)
    s = model.inner_solver(0)
    assert st.m == 3
    torch.testing.assert_close(st.mu_r_hat, discounted_demo_feature_sums(
        demos, s.reward_basis, GAMMA).mean(0))
    torch.testing.assert_close(st.cost_accrual, discounted_demo_feature_sums(
        demos, s.cost_basis, GAMMA).mean(0))
    sol = model.solve(0, torch.tensor([1.0, 1, 1, 1, -1], dtype=torch.float64),
                      torch.zeros(201, dtype=torch.float64))
    assert sol.mu_r.shape == (4,) and sol.mu_c.shape == (201,)
    with pytest.raises(ValueError, match="no solver"):
        model.solve(1, torch.zeros(5), torch.zeros(201))
    with pytest.raises(ValueError, match="timesteps"):
        SACLearnerModel(solvers=[make_solver()], timesteps=-1)
    with pytest.raises(ValueError, match="non-empty list"):
        SACLearnerModel(solvers=[], timesteps=1)


@pytest.mark.parametrize("engine", ["lean", "sb3"])
def test_a_clone_is_independent_and_reproducible(engine):
    base = make_solver(3, engine)
    eta, wc = np.array([1.0, 1, 1, 1, -1]), np.zeros(201)
    before = base.policy_state()  # a copy: actor, critics and target critics
    a, b = base.clone(7), base.clone(7)
    sa, sb = a.solve(eta, wc, 60), b.solve(eta, wc, 60)
    assert a.n_updates > 0
    torch.testing.assert_close(sa.mu_c, sb.mu_c, rtol=0, atol=0)
    pa, pb = a.policy_state(), b.policy_state()
    assert pa.keys() == pb.keys() == before.keys()
    for key in pa:
        torch.testing.assert_close(pa[key], pb[key], rtol=0, atol=0, msg=key)
    # training a clone leaves the original untouched
    after = base.policy_state()
    for key in before:
        torch.testing.assert_close(before[key], after[key], rtol=0, atol=0, msg=key)
    assert base.num_timesteps == 0 and base.replay_buffer is not a.replay_buffer
    assert any(not torch.equal(before[k], pa[k]) for k in before if k.startswith("actor."))
    c = base.clone(8).solve(eta, wc, 60)
    assert not torch.equal(c.mu_c, sa.mu_c) or not torch.equal(c.mu_r, sa.mu_r)


def test_the_same_trainer_drives_sac_learners_reproducibly_and_privately(demos):
    comm = Recorder(2)
    t = trainer(demos, 0, comm)
    t.train(2)
    st = t.state
    assert torch.isfinite(st.cost_weights).all() and torch.isfinite(st.eta_bar).all()
    assert ((st.cost_weights >= 0) & (st.cost_weights <= 1)).all()
    # complete outer graph: consensus after every outer step
    torch.testing.assert_close(st.cost_weights[0], st.cost_weights[1])
    assert comm.fields <= set(ALLOWED_FIELDS)
    # a feature every learner's own pairs accrue is never a constraint (b = 0)
    everywhere = t.accrued.all(0)
    assert everywhere.any() and (st.cost_weights[:, everywhere] == 0).all()
    # the start cells (P0's support) are held at 0: at this scale they are the only cells
    # the policies accrue and the pairs do not (measured without the pin: ω_c 0.02-0.50)
    names = t.learner_model.inner_solver(0).cost_basis.names
    assert {names[j] for j in torch.nonzero(t.pinned).flatten()} == {  # ±0.25 m boxes
        f"drone{i}/cell({x},{y})" for i, xs in ((0, (0, 1)), (1, (8, 9)))
        for x in xs for y in (0, 1)}
    assert (st.cost_weights[:, t.pinned] == 0).all()
    # ... at every outer iteration, not only the last (the history's ω_c after each)
    history = torch.tensor([info["cost_weights"] for info in t.history])  # [n, L, l_c]
    assert history.shape == (len(t.history), 2, t.pinned.numel())
    assert (history[:, :, t.pinned] == 0).all()
    assert all(h > 0 for info in t.history for h in info["lga_norm"])  # the outer step moves
    again = trainer(demos, 0)
    again.train(2)
    torch.testing.assert_close(again.state.cost_weights, st.cost_weights, rtol=0, atol=0)
    torch.testing.assert_close(again.state.eta_bar, st.eta_bar, rtol=0, atol=0)


def test_mismatched_pair_counts_are_refused(demos):
    base = make_solver()
    with pytest.raises(ValueError, match="trajectory_counts says"):
        DICRL(learner_model=SACLearnerModel(solvers=[base, base.clone(1)], timesteps=1),
              shards=partition_demonstrations(demos, [1, 2]), trajectory_counts=[2, 1],
              communicator=SimulatedCommunicator(2),
              inner_schedule=CompleteSchedule(n_learners=2),
              outer_schedule=CompleteSchedule(n_learners=2))


def test_greedy_adds_only_unaccrued_features_and_keeps_the_accepted_policy(demos):
    class EveryConstraintHelps(SACGreedyConstraintInference):
        # A likelihood that rises by 1 nat per constraint: every trial is accepted.
        def mean_log_likelihood(self, solution):
            super().mean_log_likelihood(solution)
            return float(solution.cost_weights.sum())

    g = EveryConstraintHelps(solver=make_solver(5), reward_weights=[1.0, 1, 1, 1],
                             demonstrations=demos, penalty=5.0, timesteps=40,
                             max_constraints=2)
    sums = discounted_demo_feature_sums(demos, CellOccupancyCostBasis(), GAMMA)
    assert torch.equal(g.candidates, ~(sums > 0).any(0))
    res = g.run()
    assert 1 <= len(res.added) <= 2 and res.constraint_mask.sum() == len(res.added)
    assert all(g.candidates[j] for j in res.added)
    assert res.solution.solver is g.solver  # the accepted trial's policy is the current one
    with pytest.raises(ValueError, match="reward_weights"):
        SACGreedyConstraintInference(solver=make_solver(), reward_weights=[1.0],
                                     demonstrations=demos)


def _compose(*overrides):
    with initialize_config_dir(config_dir=str(ROOT / "configs"), version_base=None):
        return compose(config_name="train", overrides=["experiment=table2_quick", *overrides])


def test_table2_config_is_checked():
    import common  # experiments/ is on pytest's pythonpath
    import config_checks

    common.check_config(_compose())
    for bad, match in [("solver.timesteps=0", "solver.timesteps=0 is invalid"),
                       ("baselines.run=[ME-greedy]", r"among \['M\(C\)E-greedy'\]"),
                       ("algo.run_d_icrl=false", "without its reward"),
                       ("solver.eval_action=greedy", "'mean' or 'sampled'"),
                       ("solver.final_timesteps=0", "solver.final_timesteps=0 is invalid"),
                       ("solver.final_checks=0", "solver.final_checks=0 is invalid"),
                       ("solver.final_checks=20000",
                        r"solver.final_checks=20000 is invalid.*solver.final_timesteps=12000"),
                       ("solver.final_restarts=0", "solver.final_restarts=0 is invalid"),
                       ("solver.final_score=best", "'penalised_return' or 'learned_success'"),
                       ("solver.final_margin=0.5", "metres the last solve's penalty cells"),
                       ("solver.planner.replan=3",
                        r"solver.planner.replan=3 is invalid.*dividing solver.planner.knot=5"),
                       ("solver.planner.horizon=32", "a multiple of solver.planner.knot=5"),
                       ("+solver.solver.ent_coeff=1", "did you mean 'ent_coef'")]:
        with pytest.raises(config_checks.ConfigError, match=match):
            common.check_config(_compose(bad))


RBF = "features.cost._target_=dicrl_torch.features.drone.RBFCostBasis"


def test_a_margin_needs_a_cost_basis_that_can_grow():
    """final_margin grows the cost basis's cells: a basis without dilated() (the RBF
    bumps, no longer a config option: positive everywhere, a run refuses them) is refused
    when the task is built, naming the fix."""
    from common import drone_task

    assert drone_task(_compose("solver.final_margin=0.2")).penalty_basis.margin == 0.2
    with pytest.raises(ValueError, match="set final_margin=0"):
        drone_task(_compose(RBF, "solver.final_margin=0.2", "solver.eval_policy=sac"))
    with pytest.raises(ValueError, match="set solver.eval_policy=sac"):
        drone_task(_compose(RBF))
    with pytest.raises(ValueError, match="solver.planner.grid_step=1.0 is invalid"):
        drone_task(_compose("solver.planner.grid_step=1.0"))


TINY = ["experiment=table2_quick", "comm=simulated", "env.arena.max_steps=20", "eval_episodes=2",
        "solver.warmup_timesteps=60", "solver.timesteps=20", "solver.n_eval_episodes=1",
        "solver.final_timesteps=40", "solver.final_checks=2", "solver.final_restarts=2",
        "solver.final_score=learned_success", "solver.eval_policy=sac",
        "solver.solver.learning_starts=30", "solver.solver.batch_size=16",
        "solver.solver.net_arch=[16,16]", "algo.outer_iterations=1", "algo.inner_steps=2",
        "baselines.timesteps=20", "baselines.max_constraints=1", "logger=none"]


def test_table2_entry_point_end_to_end(tmp_path):
    out = train_cli(tmp_path, *TINY)
    assert out.returncode == 0, out.stderr[-3000:]
    res = json.loads((tmp_path / "results.json").read_text())
    methods = res["methods"]
    assert list(methods) == ["D-ICRL", "C-ICRL", "M(C)E-greedy", "Experts (ground truth)"]
    assert len(methods["D-ICRL"]["learners"]) == 2
    for name in ("D-ICRL", "C-ICRL", "M(C)E-greedy"):
        for row in methods[name]["learners"]:
            assert 0 <= row["SR"] <= 1 and 0 <= row["CVR"] <= 1
            # The table shows the mean-action rollouts (solver.eval_action), and the row
            # also holds the sampled ones, on the same episode seeds.
            assert (row["SR"], row["CVR"]) == (row["SR_mean"], row["CVR_mean"])
            assert 0 <= row["SR_sampled"] <= 1 and 0 <= row["CVR_sampled"] <= 1
            assert row["CR_mean"] is None and row["RFD"] is None
            assert 0 <= row["FPR"] <= 1 and 0 <= row["FNR"] <= 1
    assert "SR" in out.stdout and "D-ICRL 2" in out.stdout
    assert (tmp_path / "fig3b_demonstrations.png").exists()
    assert (tmp_path / "constraints_D-ICRL_1.png").exists()  # Fig. 3c, per learner


def test_table2_entry_point_with_planning_learners(tmp_path):
    """eval_policy=plan (table2_quick's): the D-ICRL and C-ICRL rows are the planners'
    (no last solve, no SAC columns), the greedy row is still SAC's."""
    small = ["solver.eval_policy=plan", "solver.planner.samples=16",
             "solver.planner.iterations=2", "solver.planner.horizon=10",
             "solver.planner.elites=4"]
    out = train_cli(tmp_path, *TINY, *small)
    assert out.returncode == 0, out.stderr[-3000:]
    res = json.loads((tmp_path / "results.json").read_text())
    for name in ("D-ICRL", "C-ICRL"):
        for row in res["methods"][name]["learners"]:
            assert (row["SR"], row["CVR"]) == (row["SR_plan"], row["CVR_plan"])
            assert 0 <= row["SR"] <= 1 and row["SR_mean"] is None
            assert row["policy_timesteps"] is None and row["final_checks"] is None
    greedy = res["methods"]["M(C)E-greedy"]["learners"][0]
    assert greedy["SR"] == greedy["SR_mean"]
    assert res["config"]["solver"]["eval_policy"] == "plan"


@pytest.fixture(scope="module")
def table2_quick_seed_0(tmp_path_factory):
    """``experiment=table2_quick`` as shipped, seed 0: ``(run dir, results, stdout)``.
    1,140 s alone on the slow 2-core machine when its planner re-planned every step (~1,060 s
    since), 1,900-2,300 s beside another job (docs/drones.md); the timeouts leave room."""
    out_dir = tmp_path_factory.mktemp("table2_quick")
    out = subprocess.run([sys.executable, str(TRAIN), f"hydra.run.dir={out_dir}",
                          "experiment=table2_quick", "seed=0"],
                         capture_output=True, text=True, cwd=ROOT, timeout=3000)
    assert out.returncode == 0, out.stderr[-3000:]
    return out_dir, json.loads((out_dir / "results.json").read_text()), out.stdout


@pytest.mark.slow
@pytest.mark.timeout(3300)
def test_table2_quick_runs_at_full_scale(table2_quick_seed_0):
    """Every row, figure and history entry of the shipped quick run."""
    out_dir, res, stdout = table2_quick_seed_0
    assert res["experiment"] == "table2_quick"
    assert len(res["history"]["D-ICRL"]) == 6
    assert all(len(h["FPR"]) == 2 for h in res["history"]["D-ICRL"])
    for name in ("D-ICRL", "C-ICRL", "M(C)E-greedy"):
        for row in res["methods"][name]["learners"]:
            assert 0 <= row["SR"] <= 1 and 0 <= row["CVR"] <= 1
            assert 0 <= row["FPR"] <= 1 and 0 <= row["FNR"] <= 1
    assert res["consensus_max_pairwise_cost_distance"] <= 1e-3
    assert all(len(h["cost_weights"]) == 2 for h in res["history"]["D-ICRL"])
    assert "FPR" in stdout and "FNR" in stdout
    for fig in ("fig3b_demonstrations", "constraints_D-ICRL_1", "constraints_D-ICRL_2",
                "constraints_C-ICRL_1", "constraints_MCE-greedy", "cost_weights"):
        assert (out_dir / f"{fig}.png").exists(), fig


@pytest.mark.slow
@pytest.mark.timeout(3300)
def test_table2_quick_meets_the_quick_targets_at_seed_0(table2_quick_seed_0):
    """Issue 26's targets for the quick config: every D-learner SR >= 0.8, CVR <= 0.15
    (seed 0 gave the exact set, and planning on it SR 1.00, CVR 0.000 for both learners
    and C-ICRL; docs/drones.md). The learned sets move with SAC's numbers, which differ
    between CPUs: the README says which figures a user can expect."""
    _, res, _ = table2_quick_seed_0
    for row in res["methods"]["D-ICRL"]["learners"]:
        assert row["SR_plan"] is not None  # the shipped config plans
        assert row["SR"] >= 0.8 and row["CVR"] <= 0.15, (row["SR"], row["CVR"])


def test_planning_on_the_true_game_flies_both_drones_round_the_block():
    """A planner given the true constraints and a door-seeking reward (what a learner with
    the exact set would hold) takes both drones to their doors in the true game, on the
    evaluation's starts, without a violation; the grid values forbid the block."""
    from common import drone_task

    task = drone_task(_compose("eval_episodes=2", "solver.eval_policy=plan"))
    truth = task.cost_basis.true_constraints().numpy()
    eta = np.array([1.0, 1.0, 1.0, 1.0, -10.0])
    row, paths = task.evaluate_planned(task.base, eta, truth.astype(np.float64), truth, seed=0)
    assert row["SR"] == 1.0 and row["CVR"] == 0.0 and row["SR_plan"] == 1.0
    assert row["SR_mean"] is None  # no SAC policy was flown
    assert len(paths) == 2
    for path in paths:
        assert not np.asarray(in_obstacle(path[:, :, :2])).any()
    values = task._grid_values(eta, truth.astype(np.float64), truth,
                               {**PLANNER_DEFAULTS}, task.base.env_factory().arena.dynamics)
    block = values[0][5 * 4 + 1, 4 * 4 + 1]  # a centre inside cell (4, 5)
    assert block < -1e8 and values[0].max() > 0


def test_every_planned_row_flies_the_same_planner_stream_in_either_backend(monkeypatch):
    """A learner's planned row does not depend on where its learner sits: all learners in
    one process (comm=simulated, learner 2 at index 1) and one per process
    (comm=distributed, index 0) plan with one seed, the one C-ICRL's row plans with."""
    from types import SimpleNamespace

    from common import drone_task

    task = drone_task(_compose("eval_episodes=2", "solver.eval_policy=plan"))
    seeds = []
    monkeypatch.setattr(task, "evaluate_planned",
                        lambda solver, eta, cw, mask, seed, progress=None:
                        (seeds.append(seed), ({}, []))[1])
    monkeypatch.setattr(task, "_bound", lambda trainer, i: None)
    dim = task.cost_basis.dim

    def holding(learners):
        n = len(learners)
        return SimpleNamespace(
            state=SimpleNamespace(eta_bar=np.ones((n, 5)), cost_weights=np.zeros((n, dim))),
            learner_model=SimpleNamespace(inner_solver=lambda i: None),
            local=list(learners), n_learners=2)

    task.evaluate_learner(holding([0, 1]), 1, progress=False)  # simulated: learner 2
    task.evaluate_learner(holding([1]), 0, progress=False)  # its own process
    task.evaluate_learner(holding([0]), 0, progress=False)  # learner 1 (and C-ICRL's)
    assert len(set(seeds)) == 1 and seeds[0] == task.planning_seed()


def test_measure_planner_reports_a_planned_true_game_row(capsys):
    """experiments/studies/measure_planner.py flies the planner on the true game with the
    true set; the same settings twice give the same flights (checksum)."""
    from studies import measure_planner  # experiments/ is on pytest's pythonpath

    small = ["--episodes", "2", "experiment=table2_quick", "solver.planner.samples=16",
             "solver.planner.iterations=1", "solver.planner.elites=4",
             "solver.planner.horizon=10"]
    rows = []
    for _ in range(2):
        measure_planner.main(small)
        rows.append(json.loads(capsys.readouterr().out.strip().splitlines()[-1]))
    assert rows[0]["episodes"] == 2 and rows[0]["planner"]["samples"] == 16
    assert 0 <= rows[0]["SR"] <= 1 and rows[0]["env_steps"] > 0
    assert rows[0]["checksum"] == rows[1]["checksum"]


def test_prune_study_counts_the_plans_that_enter_a_removed_feature(tmp_path, capsys):
    """experiments/studies/prune_study.py on a finished run's learned game (here the true
    game plus a far corner cell): the far cell is entered by no plan once removed, drone
    0's block cell by some; one JSON line per asked feature."""
    from common import drone_task
    from studies import prune_study  # experiments/ is on pytest's pythonpath

    task = drone_task(_compose())
    names = list(task.cost_basis.names)
    cw = np.where(task.cost_basis.true_constraints().numpy(), 0.8, 0.0)
    cw[names.index("drone0/cell(0,9)")] = 0.6
    row = {"reward_weights": [1.0, 1.0, 1.0, 1.0], "multiplier": -10.0}
    results = {"methods": {m: {"learners": [row]} for m in ("D-ICRL", "C-ICRL")},
               "history": {m: [{"cost_weights": [cw.tolist()]}] for m in ("D-ICRL", "C-ICRL")}}
    path = tmp_path / "results.json"
    path.write_text(json.dumps(results))
    prune_study.main([str(path), "--episodes", "2", "experiment=table2_quick",
                      "--only", "D-ICRL:0:drone0/cell(0,9)", "D-ICRL:0:drone0/cell(4,5)"])
    lines = [json.loads(x) for x in capsys.readouterr().out.strip().splitlines()]
    by = {x["feature"]: x for x in lines}
    assert set(by) == {"drone0/cell(0,9)", "drone0/cell(4,5)"}
    assert by["drone0/cell(0,9)"]["episodes_entering"] == 0 and not by["drone0/cell(0,9)"]["true"]
    assert by["drone0/cell(4,5)"]["episodes_entering"] >= 1 and by["drone0/cell(4,5)"]["true"]


def test_replan_study_flies_a_runs_learned_games_again(tmp_path, capsys):
    """experiments/studies/replan_study.py: a run's rows (here the true game's) flown by the
    planner, beside the committed SR and CVR; a results.json whose last ω_c is not the
    row's learned set is refused, not flown."""
    from common import drone_task
    from studies import replan_study  # experiments/ is on pytest's pythonpath

    task = drone_task(_compose())
    truth = task.cost_basis.true_constraints().numpy()
    cw = np.where(truth, 0.8, 0.0)
    row = {"reward_weights": [1.0, 1.0, 1.0, 1.0], "multiplier": -10.0, "SR": 0.5, "CVR": 0.25,
           "n_learned": int(truth.sum())}
    results = {"methods": {m: {"learners": [row]} for m in ("D-ICRL", "C-ICRL")},
               "history": {m: [{"cost_weights": [cw.tolist()]}] for m in ("D-ICRL", "C-ICRL")}}
    path = tmp_path / "results.json"
    path.write_text(json.dumps(results))
    replan_study.main([str(path), "experiment=table2_quick", "eval_episodes=2"])
    lines = [json.loads(x) for x in capsys.readouterr().out.strip().splitlines()]
    assert [(x["method"], x["learner"]) for x in lines] == [("D-ICRL", 1), ("C-ICRL", 1)]
    for x in lines:
        assert x["committed"] == {"SR": 0.5, "CVR": 0.25}
        assert x["now"] == {"SR": 1.0, "CVR": 0.0}  # the true game's constraints, flown
    row["n_learned"] += 1
    path.write_text(json.dumps(results))
    with pytest.raises(SystemExit, match="does not hold its final"):
        replan_study.main([str(path), "experiment=table2_quick", "eval_episodes=2"])


def test_evidence_share_counts_the_region_straight_flights_show():
    """experiments/studies/evidence_share.py on the drones' deep basis: straight flights run
    from the start support to the doors' centres; they cross the block (it sits where the
    straight routes cross), so they show part of the region, never more than the
    constrainable features cover."""
    from studies import evidence_share  # experiments/ is on pytest's pythonpath

    flights = evidence_share.straight_flights(points=5)
    starts = start_support()[:, :, :2]
    flying = flights[:, :, :, :2].max(-1) > -1  # [F, points, 2]: which drone is in the room
    assert flying.any(-1).all() and not flying.all(-1).any()  # exactly one drone at a time
    for drone in range(2):
        own = flights[flying[:, 0, drone]][:, :, drone, :2]
        assert {tuple(p) for p in own[:, 0]} == {tuple(p) for p in starts[:, drone]}
        assert np.allclose(own[:, -1, 1], 10.0) and len({tuple(p) for p in own[:, -1]}) == 1
    records = evidence_share.main(["experiment=table2_quick", "features/cost=local_relu_drones"])
    assert [r["learner"] for r in records] == [1, 2, "C-ICRL"]
    for r in records:
        assert 0.5 < r["shown_by_ignoring_flights"] <= r["expressible"] <= 1.0
