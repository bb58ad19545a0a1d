"""Discounted feature sums of demonstrations: each learner's local estimates (docs/design.md §3).

A pure function of the trajectories and a factored feature basis's output, used by the
learners' statistics (:mod:`dicrl_torch.algos.icrl`), the greedy baselines and the
experiments alike. (The drones' counterpart, counted as the SAC solver counts its
rollouts, is :func:`dicrl_torch.solvers.sac.discounted_demo_feature_sums`.)
"""

from __future__ import annotations

import torch

from dicrl_torch.demos.storage import Demonstrations
from dicrl_torch.features.bases import FactoredFeatures

__all__ = ["discounted_feature_sums", "local_estimates"]


def discounted_feature_sums(features: FactoredFeatures, demos: Demonstrations,
                            gamma: float) -> torch.Tensor:
    """Per-trajectory discounted feature sums ``Σ_t γ^t φ(s_t, a_t)``: ``[m, l]``.

    Averaged over a learner's trajectories this is ``μ̂_r^[v]`` for reward features,
    and for cost features the per-feature accrual whose dot product with ``ω_c`` is
    the local cost estimate ``b̂_ωc^[v]``."""
    cells = torch.tensor(demos.states[:, :-1])  # [m, T, N] (copies: demos are read-only)
    acts = torch.tensor(demos.actions)
    n_cells = features.local.shape[1]
    if features.local.shape[0] != demos.n_experts or n_cells != demos.n_cells:
        raise ValueError(
            f"Demonstrations of {demos.n_experts} experts on {demos.n_cells} cells do not "
            f"match features for {features.local.shape[0]} experts on {n_cells} cells.")
    phi = features.at(cells, acts, n_cells)  # [m, T, l]
    disc = gamma ** torch.arange(demos.horizon, dtype=torch.float64)
    return torch.einsum("mtl,t->ml", phi, disc)


def local_estimates(features: FactoredFeatures, demos: Demonstrations,
                    gamma: float) -> torch.Tensor:
    """``[l]`` mean discounted feature sum over ``demos`` (a learner's private shard)."""
    return discounted_feature_sums(features, demos, gamma).mean(0)
