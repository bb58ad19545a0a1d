"""The run's task surface: the :class:`~dicrl_torch.runs.task.Task` base (abstract
required methods, defaults for the optional hooks), rollouts that travel with their row
from the evaluation to its constraint map (nothing left on the task between calls), a
baseline's row given its greedy, and the continuous bases' declared optional abilities.
No solver runs here: fakes stand for the trainer, the greedy and the evaluation."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from dicrl_torch.features.continuous import (
    ContinuousFeatureBasis,
    PositionCellBasis,
    RandomFourierBasis,
)
from dicrl_torch.features.drone import (
    CellOccupancyCostBasis,
    DoorLocationRewardBasis,
    RBFCostBasis,
)
from dicrl_torch.logger import NullLogger
from dicrl_torch.runs.checkpoints import Checkpoints
from dicrl_torch.runs.runner import RunSettings, evaluate_method, run_baselines
from dicrl_torch.runs.task import Task

MAP = np.zeros((4, 4, 3), dtype=np.uint8)


class MinimalTask(Task):
    """Only the required methods: every hook is the base's."""

    columns = ("CVR",)

    def __init__(self) -> None:
        self.split, self.shards, self.demos = [1, 1], [None, None], None

    def describe(self) -> str:
        return "two learners of nothing"

    def learner_model(self, local_ids, shards, stream):
        raise AssertionError("no trainer is built here")

    def outer_metrics(self, trainer, rollouts: bool) -> dict[str, list]:
        return {}

    def evaluate_learner(self, trainer, i: int, progress: bool = True):
        """Learner ``i``'s row and one rollout ``[2, 1, 2]`` filled with its outer
        iteration and ``i``: each evaluation's own."""
        n = trainer.state.outer_iteration
        return {"CVR": float(i), "evaluated_at": n}, [np.full((2, 1, 2), 10.0 * n + i)]

    def evaluation_settings(self) -> dict:
        return {"episodes": 1}


class DrawingTask(MinimalTask):
    """Draws a map and keeps what each one was given, for the test to read."""

    def __init__(self) -> None:
        super().__init__()
        self.drawn: list[tuple[str, list[np.ndarray]]] = []

    def constraint_map(self, label, row, rollouts=()):
        self.drawn.append((label, [np.array(r) for r in rollouts]))
        return MAP


def test_the_base_declares_the_required_methods_and_defaults_the_hooks(tmp_path, capsys):
    class Incomplete(Task):
        def describe(self) -> str:
            return ""

    with pytest.raises(TypeError, match="evaluate_learner"):
        Incomplete()
    task = MinimalTask()
    task.announce(tmp_path)
    assert capsys.readouterr().out == "two learners of nothing\n"
    task.bind_run_dir(tmp_path, {}, process=1, processes=2)
    assert task.constraint_map("x", {}) is None and task.constraint_map("x", {}, ()) is None
    assert task.row_scalars({}) == [] and task.reference_rows() == {}
    assert task.annotate({}) is None and task.make_baselines({}) == {}
    assert task.figures(methods={}, histories={}, experiment="e", eval_every=1) == {}
    with pytest.raises(NotImplementedError, match="baseline_row"):
        task.baseline_row("B", object(), object())


def _settings() -> RunSettings:
    return RunSettings(experiment="surface", config={}, training_config={"run": "surface"},
                       outer_iterations=2)


def _evaluate(task: Task, ckpt: Checkpoints, n: int, out: Path) -> list[dict]:
    trainer = SimpleNamespace(state=SimpleNamespace(outer_iteration=n), local=[0, 1])
    return evaluate_method("D-ICRL", trainer, task=task, settings=_settings(), ckpt=ckpt,
                           logger=NullLogger(), run_of=lambda v: f"learner{v}", out=out)


def test_each_rows_map_gets_that_rows_rollouts_and_nothing_is_left_behind(tmp_path):
    """Two successive evaluations share nothing: each row's map is drawn with the
    rollouts that row was measured on, whatever was evaluated in between; a row taken
    from the checkpoint is drawn with none (not with the last evaluation's)."""
    task = DrawingTask()
    ckpt = Checkpoints(tmp_path / "checkpoint.pt", False, config={"run": "surface"})
    first = _evaluate(task, ckpt, 1, tmp_path)
    second = _evaluate(task, ckpt, 2, tmp_path)
    assert [r["evaluated_at"] for r in first + second] == [1, 1, 2, 2]
    drawn = [(label, [float(r.flat[0]) for r in rollouts]) for label, rollouts in task.drawn]
    assert drawn == [("D-ICRL learner 1", [10.0]), ("D-ICRL learner 2", [11.0]),
                     ("D-ICRL learner 1", [20.0]), ("D-ICRL learner 2", [21.0])]
    assert vars(task).keys() == {"split", "shards", "demos", "drawn"}  # nothing else kept
    # Resumed after outer iteration 2: the rows come from the checkpoint, without rollouts.
    task.drawn.clear()
    again = _evaluate(task, ckpt, 2, tmp_path)
    assert again == second
    assert task.drawn == [("D-ICRL learner 1", []), ("D-ICRL learner 2", [])]
    assert (tmp_path / "constraints_D-ICRL_2.png").exists()


def test_a_task_without_a_map_logs_its_rows_without_one(tmp_path):
    ckpt = Checkpoints(tmp_path / "checkpoint.pt", False, config={"run": "surface"})
    rows = _evaluate(MinimalTask(), ckpt, 1, tmp_path)
    assert [r["CVR"] for r in rows] == [0.0, 1.0]
    assert not list(tmp_path.glob("constraints_*.png"))


class FakeGreedy:
    """A baseline that adds ``k`` constraints; its ``rollout`` marks its own paths."""

    resumable = True

    def __init__(self, k: int, mark: float) -> None:
        self.k, self.rollout = k, np.full((2, 1, 2), mark)

    def run(self, resume_from=None, on_step=None):
        return SimpleNamespace(added=list(range(self.k)), seconds=0.5)


class BaselineTask(DrawingTask):
    def make_baselines(self, methods, progress=True):
        return {"G1": FakeGreedy(1, 7.0), "G2": FakeGreedy(2, 8.0)}

    def baseline_row(self, name, greedy, result):
        """The row of the greedy it is handed (no lookup on the task)."""
        history = [{"step": k, "FPR": 0.0} for k in range(len(result.added) + 1)]
        return {"n_learned": len(result.added)}, history, [greedy.rollout]


def test_a_baselines_row_is_given_its_greedy_and_its_map_that_rows_rollouts(tmp_path):
    task = BaselineTask()
    ckpt = Checkpoints(tmp_path / "checkpoint.pt", False, config={"run": "surface"})
    methods, histories, seconds = run_baselines(task, {}, logger=NullLogger(), out=tmp_path,
                                                ckpt=ckpt)
    assert [m["learners"][0]["n_learned"] for m in methods.values()] == [1, 2]
    assert [len(h) for h in histories.values()] == [2, 3] and seconds == {"G1": 0.5,
                                                                         "G2": 0.5}
    assert [(label, float(r[0].flat[0])) for label, r in task.drawn] == [("G1", 7.0),
                                                                         ("G2", 8.0)]


# ------------------------------------------------------------------ basis abilities
def _states(n: int, agents: int, seed: int = 0) -> np.ndarray:
    """``[n, agents, 4]`` float64 joint states inside the drone room."""
    return np.random.default_rng(seed).uniform(0.0, 10.0, size=(n, agents, 4))


def test_the_generic_abilities_are_the_plain_computation():
    """A basis without a faster path: numpy_features is compute, dot its weighted sum
    (bit for bit), no margin to grow, no cells."""
    basis = RandomFourierBasis(n_agents=2, state_dim=4, n_features=8, seed=3)
    states = _states(5, 2)
    phi = basis.compute(torch.as_tensor(states)).numpy()
    np.testing.assert_array_equal(basis.numpy_features(states), phi)
    w = np.linspace(0.0, 1.0, basis.dim)
    np.testing.assert_array_equal(basis.dot(states, w), phi @ w)
    assert not basis.dilatable and basis.cell_rectangles().shape == (0, 4)
    with pytest.raises(NotImplementedError, match="dilatable"):
        basis.dilated(0.1)


def test_the_drone_bases_keep_their_fast_paths_and_abilities():
    """The fast numpy paths stay where they were (equal to the generic computation); the
    cell basis alone can grow by a margin."""
    states = _states(64, 2, seed=1)
    door = DoorLocationRewardBasis()
    np.testing.assert_array_equal(door.numpy_features(states),
                                  door.compute(torch.as_tensor(states)).numpy())
    cells, rbf = CellOccupancyCostBasis(), RBFCostBasis()
    w = np.random.default_rng(2).uniform(size=cells.dim)
    np.testing.assert_allclose(cells.dot(states, w),
                               cells.compute(torch.as_tensor(states)).numpy() @ w,
                               rtol=0, atol=1e-12)
    assert type(cells).dot is not ContinuousFeatureBasis.dot  # the look-up, kept
    assert type(door).numpy_features is not ContinuousFeatureBasis.numpy_features
    assert cells.dilatable and cells.dilated(0.2).margin == 0.2
    assert not rbf.dilatable
    grid = PositionCellBasis(n_agents=2, bounds=((-1, 1), (-1, 1)), proximity_radius=0.1,
                             n_per_axis=4)
    assert grid.cell_rectangles().shape == (16, 4) and not grid.dilatable


class FixedStartTask(MinimalTask):
    """A task that fixes η(0), ω_c(0) (as a SAC warm-up does), over tiny_dicrl's grid."""

    def __init__(self) -> None:
        import tiny_dicrl

        self.solver, self.rb, self.cb, self.shards = tiny_dicrl.build_tiny()
        self.split, self.demos = list(tiny_dicrl.SPLIT), None

    def learner_model(self, local_ids, shards, stream):
        from dicrl_torch.algos.models import TabularLearnerModel

        return TabularLearnerModel(solver=self.solver, reward_basis=self.rb,
                                   cost_basis=self.cb)

    def initial_weights(self) -> dict[str, float]:
        return {"init_reward_weights": 0.5, "init_multiplier": -2.0, "init_cost_weights": 0.25}


def _spec(**options):
    from dicrl_torch.algos.dicrl import StepSizes
    from dicrl_torch.comm.graphs import CompleteSchedule
    from dicrl_torch.runs.runner import TrainerSpec

    return TrainerSpec(schedules=lambda n: (CompleteSchedule(n_learners=n),) * 2,
                       steps=StepSizes(alpha_bar=0.02), inner_step=0.005, n_shards=3,
                       options=dict(inner_steps=2, **options))


def test_trainers_start_from_the_tasks_initial_weights_given_once():
    from dicrl_torch.comm import SimulatedCommunicator
    from dicrl_torch.runs.runner import make_trainer

    task = FixedStartTask()
    trainer = make_trainer(task, _spec(), task.shards, SimulatedCommunicator(n_learners=3),
                           task.split, stream=0, progress=False)
    eta, cost = trainer.state.eta, trainer.state.cost_weights  # [..., l_r + 1], [N_L, d]
    assert torch.all(eta[..., :-1] == 0.5) and torch.all(eta[..., -1] == -2.0)
    assert set(cost.unique().tolist()) == {0.0, 0.25}  # the start cells' pinned at 0
    # the same value given again is fine; another one is refused, naming the fix
    make_trainer(task, _spec(init_multiplier=-2.0), task.shards,
                 SimulatedCommunicator(n_learners=3), task.split, stream=0, progress=False)
    with pytest.raises(ValueError, match="init_multiplier.*give it once"):
        make_trainer(task, _spec(init_multiplier=-1.0), task.shards,
                     SimulatedCommunicator(n_learners=3), task.split, stream=0,
                     progress=False)
