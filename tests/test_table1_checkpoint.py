"""The committed 3-expert Table 1 checkpoints (docs/table1_run) still load into the
current code and resume, whatever modules moved: the config they were written under is
the one experiment=table1 composes today, every trainer state loads into a trainer built
by today's runner, the evaluated rows are found under today's evaluation settings, and
every greedy progress record is accepted."""

from __future__ import annotations

from pathlib import Path

import common  # experiments/ is on pytest's pythonpath
import numpy as np
import pytest
from hydra import compose, initialize_config_dir

from dicrl_torch.comm import SimulatedCommunicator
from dicrl_torch.demos.storage import Demonstrations
from dicrl_torch.runs.checkpoints import Checkpoints
from dicrl_torch.runs.runner import make_trainer

ROOT = Path(__file__).resolve().parents[1]
RUN = ROOT / "docs" / "table1_run"


def table1_config(*overrides: str):
    with initialize_config_dir(config_dir=str(ROOT / "configs"), version_base="1.3"):
        return compose(config_name="train", overrides=["experiment=table1", *overrides])


class LearnerSide:
    """The table1 grid task's learner side only: its experts' solves (minutes at 3
    experts) are not needed to load a checkpoint."""

    def __init__(self, cfg):
        from dicrl_torch.runs.grid import GridTask

        g = common.build_grid(cfg)
        self.model, self.split = g.model, list(cfg.split)
        self.learner_model = lambda ids, shards, stream: GridTask.learner_model(
            g, ids, shards, stream)
        self.evaluation_settings = lambda: {
            "threshold": float(cfg.algo.threshold), "eval_episodes": int(cfg.eval_episodes),
            "prune_min_gain": float(cfg.algo.prune_min_gain)}
        self.initial_weights = dict  # the grid task's: the trainer spec's options decide

    def standing_still(self, m: int) -> Demonstrations:
        """``m`` trajectories that stay in the start cells: a trainer's fingerprint needs
        only the counts (the state's statistics are not checked)."""
        T, start = self.model.horizon, np.asarray(self.model.start_state)
        return Demonstrations(states=np.broadcast_to(start, (m, T + 1, len(start))).copy(),
                              actions=np.zeros((m, T, len(start)), dtype=np.int64),
                              n_cells=self.model.n_cells, n_actions=self.model.n_actions)


@pytest.mark.parametrize("path,methods", [
    (RUN / "checkpoint.pt", ["D-ICRL", "C-ICRL", "ME-greedy", "MCE-greedy"]),
    (RUN / "c_icrl" / "checkpoint.pt", ["C-ICRL"]),
    (RUN / "greedy_me" / "checkpoint.pt", ["ME-greedy"]),
    (RUN / "greedy_mce" / "checkpoint.pt", ["MCE-greedy"]),
])
def test_committed_table1_checkpoints_load_and_resume(path, methods):
    cfg = table1_config()
    settings = common.run_settings(cfg)
    # Refused if the config they were written under differs from today's experiment=table1.
    ckpt = Checkpoints(path, True, config=settings.training_config)
    task = LearnerSide(cfg)
    spec = common.trainer_spec(cfg)
    for name in methods:
        states = ckpt.states(name)
        assert states, f"{path} holds no {name}"
        if name.endswith("greedy"):
            assert states[0]["greedy"]["evaluated"] >= 1  # resumable progress record
            continue
        counts = task.split if name == "D-ICRL" else [sum(task.split)]
        trainer = make_trainer(task, spec, [task.standing_still(m) for m in counts],
                               SimulatedCommunicator(n_learners=len(counts)), counts,
                               stream=0, progress=False)
        trainer.load_state_dict(states[0])  # refused if today's trainer differs
        assert trainer.state.outer_iteration == cfg.algo.outer_iterations == 20
        if path == RUN / "checkpoint.pt":  # the merged run was evaluated (pruning: minutes
            # per learner at 3 experts); its resume reuses the rows
            rows = ckpt.evaluated_rows(name, 20, task.evaluation_settings())
            assert rows is not None and len(rows) == len(counts)
