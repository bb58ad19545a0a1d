"""The tiny ``experiments/train.py`` job shared by the config, resume and robustness tests:
1 expert, T = 8, 2 learners, 3 outer iterations; and the composed ``train`` config, for
tests that check a configuration without running it.

The job runs in this process (:func:`train_here`: the entry point's own ``train`` on the
composed config) unless a test needs a process boundary: fault injection that kills the
process (``env``), or ``subprocess=True``."""

from __future__ import annotations

import contextlib
import io
import json
import os
import signal
import subprocess
import subprocess as _subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
TRAIN = ROOT / "experiments" / "train.py"
TINY = ["env.layout.n_experts=1", "env.model.horizon=8", "solver.compile=false",
        "algo.outer_iterations=3", "algo.inner_steps=2", "eval_episodes=10",
        "n_demonstrations=10", "split=[4,6]", "logger=none"]


class SimulatedKill(BaseException):
    """``kill -9`` of the process, as :func:`train_here` plays it: raised where the process
    would have died, and caught by nothing but :func:`train_here` (a BaseException)."""


@contextlib.contextmanager
def killed_where_it_kills_itself(crash_after: str | None):
    """With ``crash_after`` (``DICRL_CRASH_AFTER``'s value), the checkpoints' fault
    injection, which would SIGKILL this process, raises :class:`SimulatedKill` instead:
    the run stops right after the atomic checkpoint write, as the process would."""
    if crash_after is None:
        yield
        return
    real_kill, before = os.kill, os.environ.get("DICRL_CRASH_AFTER")

    def kill(pid: int, sig: int) -> None:
        if pid == os.getpid() and sig == signal.SIGKILL:
            raise SimulatedKill
        real_kill(pid, sig)

    os.environ["DICRL_CRASH_AFTER"], os.kill = crash_after, kill
    try:
        yield
    finally:
        os.kill = real_kill
        if before is None:
            os.environ.pop("DICRL_CRASH_AFTER")
        else:
            os.environ["DICRL_CRASH_AFTER"] = before


def train_here(run_dir: Path, *overrides: str, crash_after: str | None = None
               ) -> subprocess.CompletedProcess:
    """``experiments/train.py`` with ``overrides`` into ``run_dir``, in this process: the
    same config composition, checks, launcher and exit code, without a Python start-up.
    Its output is captured; torch's thread count and the signal handlers are restored.
    ``crash_after`` plays ``DICRL_CRASH_AFTER`` (kill -9 after that checkpoint): the
    return code is then -9, as for the process."""
    import train  # experiments/ is on pytest's pythonpath

    run_dir = Path(run_dir)
    hydra_overrides = [o for o in overrides if o.startswith("hydra.")]
    if hydra_overrides:
        raise ValueError(f"{hydra_overrides}: a Hydra setting needs the real command line; "
                         f"use subprocess=True.")
    out, err = io.StringIO(), io.StringIO()
    threads = torch.get_num_threads()
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                with killed_where_it_kills_itself(crash_after):
                    code = train.train(compose_train(*overrides), run_dir, tuple(overrides))
            except SimulatedKill:
                code = -signal.SIGKILL
            except SystemExit as e:
                code = e.code if isinstance(e.code, int) else 1
                if not isinstance(e.code, int | None):
                    print(e.code, file=sys.stderr)
            except Exception as e:  # noqa: BLE001 - reported as a failed run, as a CLI would
                import traceback

                traceback.print_exc()
                code = 1
                print(f"{type(e).__name__}: {e}", file=sys.stderr)
    finally:
        torch.set_num_threads(threads)
        for sig, handler in handlers.items():
            signal.signal(sig, handler)
    return subprocess.CompletedProcess(["train.py", *overrides], code or 0, out.getvalue(),
                                       err.getvalue())


def train_cli(run_dir: Path, *overrides: str, env: dict | None = None,
              timeout: float = 600, subprocess: bool = False) -> subprocess.CompletedProcess:
    """``python experiments/train.py hydra.run.dir=RUN_DIR OVERRIDES``; its output captured.

    In this process (:func:`train_here`) unless a process boundary is what the test needs:
    ``subprocess``, learner processes (``comm=distributed``), a signal other than SIGKILL
    or a crash of one learner process in ``env``, or a Hydra setting. A ``kill -9`` by
    ``DICRL_CRASH_AFTER`` of a one-process run is played in-process (:class:`SimulatedKill`).
    """
    env = dict(env or {})
    crash_after = env.pop("DICRL_CRASH_AFTER", None)
    boundary = (subprocess or env or "comm=distributed" in overrides
                or "@rank" in (crash_after or "")
                or any(o.startswith("hydra.") for o in overrides))
    if not boundary:
        return train_here(run_dir, *overrides, crash_after=crash_after)
    if crash_after is not None:
        env["DICRL_CRASH_AFTER"] = crash_after
    return run_process(run_dir, *overrides, env=env, timeout=timeout)


def run_train(run_dir: Path, *extra: str, **how) -> subprocess.CompletedProcess:
    """The TINY job plus ``extra`` overrides in ``run_dir`` (see :func:`train_cli`)."""
    return train_cli(run_dir, *TINY, *extra, **how)


def run_process(run_dir: Path, *overrides: str, env: dict | None = None,
                timeout: float = 600) -> subprocess.CompletedProcess:
    """``experiments/train.py`` with ``overrides`` as a process of its own."""
    return _subprocess.run(
        [sys.executable, str(TRAIN), f"hydra.run.dir={run_dir}", *overrides],
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
