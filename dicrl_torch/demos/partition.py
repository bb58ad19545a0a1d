"""Splitting demonstrations over learners (DESIGN §3: 100 split 10/20/30/40)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .npz import shard_indices
from .storage import Demonstrations

PAPER_SPLIT: tuple[int, ...] = (10, 20, 30, 40)


def partition_demonstrations(
    demos: Demonstrations,
    sizes: Sequence[int],
    *,
    rng: np.random.Generator | None = None,
) -> list[Demonstrations]:
    """Split the ``m`` trajectories into consecutive, disjoint shards.

    Args:
        demos: ``m`` trajectories (``states [m, T+1, N]``, ``actions [m, T, N]``).
        sizes: shard sizes, one per learner, positive and summing to ``m``
            (e.g. :data:`PAPER_SPLIT`).
        rng: when given, the trajectories are shuffled with it first; otherwise shard
            ``k`` holds trajectories ``sum(sizes[:k]) .. sum(sizes[:k+1]) - 1``.

    Returns:
        ``len(sizes)`` demonstrations; shard ``k`` has ``sizes[k]`` trajectories.
    """
    if not isinstance(demos, Demonstrations):
        raise TypeError(f"demos must be a Demonstrations, got {type(demos).__name__}.")
    return [demos.subset(idx)
            for idx in shard_indices(demos.n_trajectories, sizes, rng, "trajectories")]
