"""One protocol for every set of demonstrations (docs/design.md §3, §7).

The grid world's :class:`~dicrl_torch.demos.storage.Demonstrations` (cells and actions
of ``N`` experts) and the drone arena's
:class:`~dicrl_torch.demos.drone_demos.DroneDemonstrations` (positions, velocities and
commands of a pair of drones) differ in what a step holds but not in how a set of them
is counted, split over learners and compared: that is :class:`Trajectories`, and
:class:`TrajectoryArrays` is the code the two frozen dataclasses share for it.
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar, Protocol, Self, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike

from dicrl_torch.demos.npz import subset_indices

__all__ = ["TrajectoryArrays", "Trajectories"]


@runtime_checkable
class Trajectories(Protocol):
    """A set of ``m`` demonstrated trajectories that can be split over learners
    (:func:`~dicrl_torch.demos.partition.partition_demonstrations`)."""

    @property
    def n_trajectories(self) -> int:
        """``m``."""
        ...

    def subset(self, indices: ArrayLike) -> Self:
        """The trajectories at ``indices`` (1-D ints, in that order, or a ``[m]`` bool
        mask) as a new set of the same kind."""
        ...


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return a is not None and b is not None and np.array_equal(a, b)
    return a == b


class TrajectoryArrays:
    """What a frozen dataclass of trajectory arrays (``states [m, T+1, ...]``,
    ``actions [m, T, ...]`` and the fields named in :attr:`per_trajectory`, indexed by
    trajectory first) gets for :class:`Trajectories`: the counts, :meth:`subset` (the
    subset is validated anew by the class's constructor) and equality by content (hence
    unhashable)."""

    per_trajectory: ClassVar[tuple[str, ...]] = ("states", "actions")
    """Fields whose first axis is the trajectory (a None field stays None)."""
    unit: ClassVar[str] = "trajectories"
    """What messages call the trajectories."""

    @property
    def n_trajectories(self) -> int:
        """``m``."""
        return self.states.shape[0]

    @property
    def horizon(self) -> int:
        """``T``, the number of steps (decisions) per trajectory, padded to the longest."""
        return self.actions.shape[1]

    def subset(self, indices: ArrayLike) -> Self:
        """The trajectories at ``indices`` (1-D ints, in that order, or a ``[m]`` bool
        mask) as new demonstrations."""
        idx = subset_indices(indices, self.n_trajectories)
        return dataclasses.replace(self, **{
            name: None if getattr(self, name) is None else getattr(self, name)[idx]
            for name in self.per_trajectory})

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, type(self)):
            return NotImplemented
        return all(_same(getattr(self, f.name), getattr(other, f.name))
                   for f in dataclasses.fields(self))

    __hash__ = None  # type: ignore[assignment]  # mutable-by-content arrays: unhashable
