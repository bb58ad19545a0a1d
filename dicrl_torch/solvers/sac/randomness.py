"""The SAC solver's random streams, swapped in and out and saved without pickling.

SB3 draws from the legacy global generators (torch, numpy's ``np.random``, python's
``random``); the solver keeps private copies of them and swaps them in only while SB3
runs (:mod:`dicrl_torch.solvers.sac`, "Private randomness"). This module captures,
restores and seeds those global streams, and turns them and numpy ``Generator`` s into
plain data (tensors, ints, floats, strings, lists, dicts) that ``torch.load(...,
weights_only=True)`` reads back, for :meth:`SACConstrainedSolver.state_dict`.
"""

from __future__ import annotations

import random
from typing import Any

import numpy as np
import torch

from dicrl_torch.envs.vector import generator_state_dict, restore_generator

__all__ = [
    "capture_global_rng",
    "generator_state_dict",
    "global_rng_from_state_dict",
    "global_rng_state_dict",
    "restore_generator",
    "restore_global_rng",
    "seed_global_rng",
]


# SB3 draws from the legacy global generators; these swap them (NPY002 is intended).
def capture_global_rng(cuda: bool) -> tuple[Any, ...]:
    """The global torch (CPU, and every CUDA device's when ``cuda``), numpy and
    ``random`` states."""
    return (torch.get_rng_state(), torch.cuda.get_rng_state_all() if cuda else None,
            np.random.get_state(), random.getstate())  # noqa: NPY002


def restore_global_rng(state: tuple[Any, ...], cuda: bool) -> None:
    """Set the global streams to a :func:`capture_global_rng` state."""
    torch.set_rng_state(state[0])
    if cuda:
        torch.cuda.set_rng_state_all(state[1])
    np.random.set_state(state[2])  # noqa: NPY002
    random.setstate(state[3])


def seed_global_rng(seed: int) -> None:
    """Seed the global streams from ``seed`` (as the solver's first SB3 run does)."""
    torch.manual_seed(seed)
    np.random.seed(seed % 2**32)  # noqa: NPY002 (private, restored)
    random.seed(seed)


# ------------------------------------------------------------------ as plain data
def global_rng_state_dict(state: tuple[Any, ...] | None) -> dict[str, Any] | None:
    """A :func:`capture_global_rng` state (or None: not drawn from yet) as plain data."""
    if state is None:
        return None
    torch_cpu, torch_cuda, np_state, py_state = state
    name, key, pos, has_gauss, cached_gaussian = np_state
    version, internal, gauss_next = py_state
    return {
        "torch": torch_cpu.clone(),
        "torch_cuda": None if torch_cuda is None else [s.clone() for s in torch_cuda],
        "numpy": {"bit_generator": str(name),
                  "key": torch.from_numpy(np.asarray(key, dtype=np.int64)),
                  "pos": int(pos), "has_gauss": int(has_gauss),
                  "cached_gaussian": float(cached_gaussian)},
        "random": {"version": int(version),
                   "internal": torch.tensor(internal, dtype=torch.int64),
                   "gauss_next": None if gauss_next is None else float(gauss_next)},
    }


def global_rng_from_state_dict(sd: dict[str, Any] | None, cuda: bool) -> tuple[Any, ...] | None:
    """The inverse of :func:`global_rng_state_dict`, for :func:`restore_global_rng`."""
    if sd is None:
        return None
    if cuda != (sd["torch_cuda"] is not None):
        saved = "CUDA" if sd["torch_cuda"] is not None else "CPU"
        raise ValueError(
            f"The saved global random streams are for a {saved} solver, this solver runs "
            f"on {'CUDA' if cuda else 'the CPU'}; load it into a solver on the same kind of "
            f"device.")
    n, r = sd["numpy"], sd["random"]
    np_state = (n["bit_generator"], n["key"].numpy().astype(np.uint32), int(n["pos"]),
                int(n["has_gauss"]), float(n["cached_gaussian"]))
    py_state = (int(r["version"]), tuple(int(x) for x in r["internal"].tolist()),
                r["gauss_next"])
    torch_cuda = None if sd["torch_cuda"] is None else [s.clone() for s in sd["torch_cuda"]]
    return sd["torch"].clone(), torch_cuda, np_state, py_state
