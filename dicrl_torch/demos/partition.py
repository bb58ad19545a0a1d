"""Splitting demonstrations over learners (docs/design.md §3: 100 split 10/20/30/40; §7: the
drones' 9 pairs split 4/5)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TypeVar

import numpy as np

from .npz import shard_indices
from .trajectories import Trajectories

PAPER_SPLIT: tuple[int, ...] = (10, 20, 30, 40)

T = TypeVar("T", bound=Trajectories)


def partition_demonstrations(
    demos: T,
    sizes: Sequence[int],
    *,
    rng: np.random.Generator | None = None,
) -> list[T]:
    """Split the ``m`` trajectories into consecutive, disjoint shards.

    Any :class:`~dicrl_torch.demos.trajectories.Trajectories` splits the same way: the
    grid world's :class:`~dicrl_torch.demos.storage.Demonstrations` (e.g.
    :data:`PAPER_SPLIT`) and the drones'
    :class:`~dicrl_torch.demos.drone_demos.DroneDemonstrations`, whose trajectories are
    the pairs (e.g. ``PAPER_DRONE_SPLIT``).

    Args:
        demos: ``m`` trajectories.
        sizes: shard sizes, one per learner, positive and summing to ``m``.
        rng: when given, the trajectories are shuffled with it first; otherwise shard
            ``k`` holds trajectories ``sum(sizes[:k]) .. sum(sizes[:k+1]) - 1``.

    Returns:
        ``len(sizes)`` demonstrations of ``demos``' kind; shard ``k`` has ``sizes[k]``
        trajectories.
    """
    if not isinstance(demos, Trajectories):
        raise TypeError(f"demos must be demonstrations (Demonstrations, DroneDemonstrations: "
                        f"a Trajectories), got {type(demos).__name__}.")
    unit = getattr(demos, "unit", "trajectories")
    return [demos.subset(idx) for idx in shard_indices(demos.n_trajectories, sizes, rng, unit)]
