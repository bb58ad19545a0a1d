"""Re-solve studies on a finished SAC run's checkpoint (docs/drones.md, 2026-12-05).

    # Pruning by re-solve: free each learned feature (ω_c >= 0.5) in turn and count how
    # often the re-solved policy visits it (20 rollouts after 1,000 and 2,000 steps).
    .venv/bin/python experiments/studies/resolve_study.py prune RUN_DIR [--methods D-ICRL,C-ICRL]
    # The last solve of one learner again, with solver settings changed for it only.
    .venv/bin/python experiments/studies/resolve_study.py last-solve RUN_DIR D-ICRL 0 \\
        demo_value_bound=true
    .venv/bin/python experiments/studies/resolve_study.py last-solve RUN_DIR C-ICRL 0 \\
        final_margin=0.2
    .venv/bin/python experiments/studies/resolve_study.py last-solve RUN_DIR D-ICRL 0 \\
        eval_policy=plan planner.samples=128 planner.iterations=3

RUN_DIR is a Hydra run directory of ``experiments/train.py`` (its ``.hydra/config.yaml`` and
``checkpoint.pt``). The trainers are rebuilt from the config and loaded from the end of
training; no warm-up runs (the solvers' states come from the checkpoint). Prints one JSON
line per measurement. Run with ``DICRL_THREADS=1`` beside another job.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
from pathlib import Path

import torch
from omegaconf import OmegaConf

from dicrl_torch.comm import SimulatedCommunicator
from dicrl_torch.runs.checkpoints import Checkpoints
from dicrl_torch.runs.runner import make_trainer

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # experiments/: common.py
from common import build_task, trainer_spec  # noqa: E402

SETTINGS = {"demo_bc": float, "demo_value_bound": lambda v: {"true": True, "false": False}[v],
            "final_margin": float, "eval_policy": str, "planner.samples": int,
            "planner.iterations": int, "planner.elites": int, "eval_episodes": int}
SOLVER_SETTINGS = ("demo_bc", "demo_value_bound")
"""Settings of the learner's trained solver (the rest are the task's: config keys)."""
TASK_KEYS = {"final_margin": "solver.final_margin", "eval_policy": "solver.eval_policy",
             "eval_episodes": "eval_episodes"}  # planner.X: solver.planner.X


def load(run: Path, method: str, task_settings: dict | None = None):
    """``(task, trainer)`` of ``method`` (``D-ICRL`` or ``C-ICRL``) at the end of training,
    the task built from the run's config with ``task_settings`` (SETTINGS' keys) changed."""
    cfg = OmegaConf.load(run / ".hydra" / "config.yaml")
    if "warmup_timesteps" in cfg.solver:  # a SAC run's
        # The checkpoint holds the trained solvers: no warm-up to train (or to load).
        cfg.solver.warmup_timesteps = 0
    for key, value in (task_settings or {}).items():
        if key.startswith("planner.") and cfg.solver.get("planner") is None:
            cfg.solver.planner = {}
        OmegaConf.update(cfg, TASK_KEYS.get(key, f"solver.{key}"), value)
    task = build_task(cfg)
    spec = trainer_spec(cfg)
    with contextlib.redirect_stdout(sys.stderr):  # its "resuming from" line: not a result
        states = Checkpoints(run / "checkpoint.pt", resume=True).states(method)
    if not states:
        ranks = " (a comm=distributed run keeps each D-learner in checkpoint_rank<v>.pt; " \
                "rerun it with comm=simulated)" if (run / "checkpoint_rank0.pt").exists() else ""
        sys.exit(f"error: {run / 'checkpoint.pt'} holds no {method} state{ranks}.")
    if method == "D-ICRL":
        trainer = make_trainer(task, spec, task.shards, SimulatedCommunicator(len(task.split)),
                               task.split, stream=0, progress=False)
    else:
        trainer = make_trainer(task, spec, [task.demos], SimulatedCommunicator(1),
                               [sum(task.split)], stream=1, progress=False)
    trainer.load_state_dict(states[0])
    return task, trainer


def prune(run: Path, methods: list[str], threshold: float = 0.5) -> None:
    for method in methods:
        task, trainer = load(run, method)
        names = task.cost_basis.names
        for i in range(len(trainer.local)):
            eta, cw = trainer.state.eta_bar[i], trainer.state.cost_weights[i]
            solver = trainer.learner_model.inner_solver(i)
            for j in torch.nonzero(cw >= threshold).flatten().tolist():
                t0 = time.perf_counter()
                clone = solver.clone(1234 + j)  # the learner's own solver stays as saved
                freed = cw.clone()
                freed[j] = 0.0
                visits = [float(clone.solve(eta, freed, 1000, n_eval_episodes=20).mu_c[j])
                          for _ in range(2)]
                print(json.dumps({
                    "method": method, "learner": i + 1, "feature": names[j],
                    "true": bool(task.true[j]), "cost_weight": round(float(cw[j]), 3),
                    "multiplier": round(float(eta[-1]), 2),
                    "visits_after_1000": round(visits[0], 3),
                    "visits_after_2000": round(visits[1], 3),
                    "seconds": round(time.perf_counter() - t0)}), flush=True)


def last_solve(run: Path, method: str, learner: int, settings: dict) -> None:
    # eval_policy=plan: no last solve, planning on the learned game.
    task, trainer = load(run, method, {k: v for k, v in settings.items()
                                       if k not in SOLVER_SETTINGS})
    solver = trainer.learner_model.inner_solver(learner)
    for key, value in settings.items():
        if key in SOLVER_SETTINGS:  # the solver's copy and its engine's update's
            setattr(solver, key, value)
            engine = solver.engine
            if hasattr(engine, "model"):  # engine=sb3
                setattr(engine.model, key, value)
            else:
                setattr(engine.sac, key, value)
                engine.demo_value_bound = solver.demo_value_bound
    # A checkpoint saved before the buffer kept the demonstrations' states: give them again
    # (the same episodes; only the states are new).
    shard = task.shards[learner] if method == "D-ICRL" else task.demos
    if solver.demo_fraction > 0:
        solver.set_demonstrations(shard)
    t0 = time.perf_counter()
    row, _ = task.evaluate_learner(trainer, learner, progress=False)
    print(json.dumps({
        "method": method, "learner": learner + 1, "settings": settings, "SR": row["SR"],
        "CVR": row["CVR"], "SR_sampled": row["SR_sampled"], "kept": row["policy_timesteps"],
        "seconds": round(time.perf_counter() - t0),
        "chunk_scores": [c["success_under_constraints"] for c in row["final_checks"] or ()]}),
        flush=True)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="study", required=True)
    p = sub.add_parser("prune", help="free each learned feature and count its visits")
    p.add_argument("run", type=Path)
    p.add_argument("--methods", default="D-ICRL,C-ICRL")
    s = sub.add_parser("last-solve", help="one learner's last solve with changed settings")
    s.add_argument("run", type=Path)
    s.add_argument("method", choices=["D-ICRL", "C-ICRL"])
    s.add_argument("learner", type=int, help="0-based, as in the trainer")
    s.add_argument("settings", nargs="*", help=f"KEY=VALUE, KEY in {sorted(SETTINGS)}")
    args = parser.parse_args(argv)
    if args.study == "prune":
        prune(args.run, args.methods.split(","))
        return
    settings = {}
    for item in args.settings:
        key, _, value = item.partition("=")
        if key not in SETTINGS:
            parser.error(f"{key!r} is not a setting this study changes; use {sorted(SETTINGS)}.")
        try:
            settings[key] = SETTINGS[key](value)
        except (KeyError, ValueError):
            parser.error(f"{item!r}: give a number for demo_bc and final_margin (metres), "
                         f"true/false for demo_value_bound, an int for planner.* and "
                         f"eval_episodes.")
    last_solve(args.run, args.method, args.learner, settings)


if __name__ == "__main__":
    main()
