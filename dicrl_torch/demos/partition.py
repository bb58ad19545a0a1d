"""Splitting demonstrations over learners (DESIGN §3: 100 split 10/20/30/40)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

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
    if rng is not None and not isinstance(rng, np.random.Generator):
        raise TypeError(
            f"rng must be a numpy.random.Generator or None, got {type(rng).__name__}; "
            f"pass np.random.default_rng(seed)."
        )
    sizes = tuple(sizes)
    if not sizes:
        raise ValueError("sizes is empty; give one positive shard size per learner.")
    bad = [s for s in sizes if isinstance(s, bool | np.bool_) or not isinstance(s, int | np.integer)
           or s <= 0]
    if bad:
        raise ValueError(f"Shard sizes must be positive ints, got {list(sizes)} (bad: {bad}).")
    m = demos.n_trajectories
    if sum(sizes) != m:
        raise ValueError(
            f"Shard sizes {list(sizes)} sum to {sum(sizes)}, but there are {m} "
            f"trajectories; make the sizes sum to {m}."
        )
    order = rng.permutation(m) if rng is not None else np.arange(m)
    bounds = np.cumsum((0,) + sizes)
    return [demos.subset(order[lo:hi]) for lo, hi in zip(bounds[:-1], bounds[1:], strict=True)]
