"""The tiny ``experiments/train.py`` job shared by the config, resume and robustness tests:
1 expert, T = 8, 2 learners, 3 outer iterations, run as a subprocess; and the composed
``train`` config, for tests that check a configuration without running it."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

from hydra import compose, initialize_config_dir

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
TRAIN = ROOT / "experiments" / "train.py"
TINY = ["env.layout.n_experts=1", "env.model.horizon=8", "solver.compile=false",
        "algo.outer_iterations=3", "algo.inner_steps=2", "eval_episodes=10",
        "n_demonstrations=10", "split=[4,6]", "logger=none"]


def run_train(run_dir: Path, *extra: str, env: dict | None = None,
              timeout: float = 600) -> subprocess.CompletedProcess:
    """Run the TINY job (plus ``extra`` overrides) in ``run_dir``; its output is captured."""
    return subprocess.run(
        [sys.executable, str(TRAIN), f"hydra.run.dir={run_dir}", *TINY, *extra],
        capture_output=True, text=True, cwd=ROOT, timeout=timeout,
        env={**os.environ, **(env or {})})


def finished_run(tmp_path_factory, name: str, *extra: str,
                 run: Callable[..., subprocess.CompletedProcess] = run_train) -> Path:
    """A module fixture's reference run: ``run`` (default :func:`run_train`) with
    ``extra`` in a fresh directory ``name``, which must succeed; its directory."""
    run_dir = tmp_path_factory.mktemp(name)
    out = run(run_dir, *extra)
    assert out.returncode == 0, out.stderr[-3000:]
    return run_dir


def compose_train(*overrides: str):
    """The ``train`` config composed with ``overrides``, as the entry point would see it."""
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        return compose(config_name="train", overrides=list(overrides))


def comparable(run_dir: Path) -> dict:
    """The run's results.json without what depends on how it was run rather than what it
    computed: its timings and whether it was resumed."""
    res = json.loads((Path(run_dir) / "results.json").read_text())
    for timing in ("wall_s", "training_s", "identifiability_s"):
        res.pop(timing, None)
    res["config"].pop("resume")
    return res
