"""The one protocol of every feature basis, grid or continuous.

A basis is a fixed (untrained) ``nn.Module`` whose features ``φ ∈ [0, max_value]^l`` are
the paper's ``φ ∈ [0, d]^l``. Two kinds serve the two environments:

- ``env_kind == "grid"`` (:class:`~dicrl_torch.features.bases.FeatureBasis`): built on a
  :class:`~dicrl_torch.envs.grid.TabularGridModel`; ``basis()`` takes no input and
  returns :class:`~dicrl_torch.features.bases.FactoredFeatures`, the features of every
  joint state-action pair in factored form: ``local`` ``[N, S1, A1, l]`` plus an
  optional ``joint`` ``[S, l_joint]`` term of the joint state (``S = S1**N``).
- ``env_kind == "continuous"`` (:class:`~dicrl_torch.features.drone.DroneFeatureBasis`):
  ``basis(states, actions=None)`` maps joint drone states ``[..., 2, 4]`` (and optional
  commands ``[..., 2, 2]``) to features ``[..., l]``.

``experiments/config_checks.py`` refuses a basis (or a solver, which declares
``env_kind`` too) whose kind is not the configured environment's.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Literal, Protocol, runtime_checkable

import torch

EnvKind = Literal["grid", "continuous"]


@runtime_checkable
class Basis(Protocol):
    """What every feature basis has (``isinstance(b, Basis)`` checks it at runtime).

    Attributes:
        dim: the number of features ``l``.
        names: ``l`` labels, one per feature (e.g. ``"cell(4,5)"``, ``"drone0/cell(3,7)"``).
        env_kind: ``"grid"`` or ``"continuous"``: the environment the basis serves (see
            the module docstring for what calling it takes and returns in each).
        max_value: the bound ``d`` of every feature: ``φ ∈ [0, d]^l``, checked on every
            call.

    A cost basis with a ground truth also has ``true_constraints()``
    (:class:`ConstraintBasis`); a learned one (``FrozenModuleBasis``) has none, and FPR
    and FNR do not apply to it.

    The optional abilities of a continuous basis are declared, with their generic
    versions, on its base class
    :class:`~dicrl_torch.features.continuous.ContinuousFeatureBasis` (callers call them,
    never probe for them): ``agent_shares(N)`` ``[l, N]`` (which agent owns each
    feature), ``numpy_features(states)`` ``[..., l]`` and ``dot(states, weights)``
    ``[...]`` (the planner's fast numpy paths; generic: through ``compute``),
    ``dilatable`` and ``dilated(margin)`` (features grown by a margin; generic: none) and
    ``cell_rectangles()`` ``[C, 4]`` (the cells of the first ``C`` features, for maps;
    generic: ``[0, 4]``).
    """

    names: Sequence[str]
    env_kind: EnvKind
    max_value: float

    @property
    def dim(self) -> int: ...

    def __call__(self, *args: Any, **kwargs: Any) -> Any: ...


@runtime_checkable
class ConstraintBasis(Basis, Protocol):
    """A :class:`Basis` that knows the true constraints of its environment."""

    def true_constraints(self) -> torch.Tensor:
        """``[l]`` bool: the features that are true constraints."""
        ...
