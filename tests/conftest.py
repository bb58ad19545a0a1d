"""Suite-wide settings and the reference runs that several test files share.

`make test` runs the suite on both cores (pytest-xdist, one worker per core); each worker,
and each process a test starts, uses one torch thread: two threads per process on two
busy cores make torch's small reductions tens of times slower, and one thread gives the
same numbers in every worker.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

os.environ.setdefault("DICRL_THREADS", "1")  # the runs tests start as processes
os.environ.setdefault("OMP_NUM_THREADS", "1")
torch.set_num_threads(1)


@pytest.fixture(scope="session")
def tiny_reference(tmp_path_factory) -> Path:
    """The uninterrupted TINY job (tests/tiny_train.py), run once per worker: the run that
    every interrupted, resumed, repeated or re-sharded TINY run must reproduce."""
    from tiny_train import finished_run

    return finished_run(tmp_path_factory, "tiny_reference")


# Modules whose tests share a module-scoped run (a reference job, trained SAC solvers, a
# built task): their tests go to one worker, so the run is computed once. Every other test
# is handed to whichever worker is free.
SHARED_FIXTURE_MODULES = {
    "test_certificate", "test_comm_distributed", "test_dicrl", "test_drone_dicrl",
    "test_drones", "test_generic_sac", "test_mpe_task", "test_own_environment",
    "test_robustness", "test_sac_runs", "test_sac_solver", "test_sac_state",
    "test_train_distributed",
}


def pytest_collection_modifyitems(config, items) -> None:
    for item in items:
        module = item.module.__name__.rpartition(".")[2]
        if module in SHARED_FIXTURE_MODULES:
            item.add_marker(pytest.mark.xdist_group(module))
