"""What resampled data do to C-ICRL's certificate on a finished grid run (docs/limitations.md,
"(3,4) missed at six seeds of ten").

    .venv/bin/python experiments/studies/bootstrap_certificate.py RUN_DIR --refits 1,2,3,4

Each refit draws the pooled demonstrations with replacement (numpy's generator seeded by the
refit number), trains C-ICRL from scratch on them with the run's settings, and certifies with
its own reward, as the run's C-ICRL row does. Refit 0 keeps the data as they are: it trains
the run's C-ICRL again (the same numbers: tested). ``--local`` instead runs one inner process
from the trained C-ICRL's warm start on each resample and certifies that reward on the run's
own data (seconds, not minutes; too local to move the reward's direction, measured).
RUN_DIR is a Hydra run directory of ``experiments/train.py`` of a grid experiment with the
certificate (its ``.hydra/config.yaml`` and ``checkpoint.pt``). Prints one JSON line per
refit: the refit's η̄, its certified features, their FPR and the reward's RFD.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from dicrl_torch.comm import SimulatedCommunicator
from dicrl_torch.demos.storage import Demonstrations
from dicrl_torch.runs.runner import make_trainer

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # experiments/: common.py
from common import trainer_spec  # noqa: E402

from studies.resolve_study import load  # noqa: E402


def resample(demos: Demonstrations, refit: int) -> Demonstrations:
    """``demos``' trajectories drawn with replacement, as many as there are (``refit`` 0:
    ``demos`` themselves)."""
    if refit == 0:
        return demos
    m = len(demos.states)
    idx = np.random.default_rng(refit).integers(0, m, m)
    return Demonstrations(states=demos.states[idx], actions=demos.actions[idx],
                          n_cells=demos.n_cells, n_actions=demos.n_actions)


def certify(task, trainer) -> dict:
    """The table row of ``trainer``'s only learner, its certificate included."""
    task.before_evaluation(trainer)
    return task.evaluate_learner(trainer, 0, progress=False)[0]


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--refits", default="1,2,3,4", help="comma-separated refit numbers")
    ap.add_argument("--local", action="store_true",
                    help="one inner process from the trained warm start per resample")
    args = ap.parse_args(argv)
    task, trained = load(args.run, "C-ICRL")
    cfg = OmegaConf.load(args.run / ".hydra" / "config.yaml")
    m = len(task.demos.states)
    for refit in (int(r) for r in args.refits.split(",")):
        t0 = time.perf_counter()
        data = resample(task.demos, refit)
        if args.local:
            trainer = trained
            own_stats, own_bar = trainer.stats, trainer.state.eta_bar
            try:
                trainer.stats = [trainer.learner_model.statistics(data)]
                bar, _ = trainer.inner_process(trainer.state.cost_weights[0],
                                               trainer.state.eta[0])
                trainer.stats, trainer.state.eta_bar = own_stats, bar  # the refit's reward
                row = certify(task, trainer)
            finally:  # the next refit starts from the trained C-ICRL again
                trainer.stats, trainer.state.eta_bar = own_stats, own_bar
            eta_bar = bar[0]
        else:
            trainer = make_trainer(task, trainer_spec(cfg), [data], SimulatedCommunicator(1),
                                   [m], stream=1, progress=False)
            trainer.train(int(cfg.algo.outer_iterations))
            row, eta_bar = certify(task, trainer), trainer.state.eta_bar[0]
        print(json.dumps({"refit": refit, "eta_bar": [round(x, 3) for x in eta_bar.tolist()],
                          "constraints": row["constraints"], "FPR": row["FPR"],
                          "RFD": row["RFD"],
                          "seconds": round(time.perf_counter() - t0)}), flush=True)


if __name__ == "__main__":
    main()
