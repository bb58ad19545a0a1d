"""Metrics of the paper (docs/design.md §6) as pure functions, and batched evaluation
rollouts in the true CMG.

- CR: total true reward of all experts in an episode (mean ± std over episodes), in
  the *true* CMG where a violator stops and earns nothing more.
- FPR = |learned \\ true| / |learned| (0 when nothing is learned).
- FNR = |true \\ learned| / |true|.
- FPR and FNR are None (not applicable) for a cost basis without a ground-truth
  constraint set (:func:`true_constraints_of`).
- CVR: mean over episodes of the fraction of experts that violate a true constraint.
- RFD = ‖ω_r − ω_rE‖ / ‖ω_rE‖.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from dicrl_torch.checks import setting_number
from dicrl_torch.envs.grid import GridLayout, TabularGridModel, decode_joint


def _as_bool(mask, name: str) -> np.ndarray:
    m = np.asarray(mask.cpu() if isinstance(mask, torch.Tensor) else mask)
    if m.dtype != bool:
        raise TypeError(f"{name} must be a boolean mask, got dtype {m.dtype}.")
    return m


def _same_shape_masks(learned, true) -> tuple[np.ndarray, np.ndarray]:
    """``learned`` and ``true`` as boolean masks of one shape (FPR and FNR compare them)."""
    learned, true = _as_bool(learned, "learned"), _as_bool(true, "true")
    if learned.shape != true.shape:
        raise ValueError(f"learned {learned.shape} and true {true.shape} masks differ in shape.")
    return learned, true


def true_constraints_of(basis) -> np.ndarray | None:
    """The ground-truth constraint set ``[l]`` bool of a cost basis, or None when the basis
    has none (e.g. ``FrozenModuleBasis``: learned features name no true constraint), for
    which FPR and FNR do not apply."""
    truth = getattr(basis, "true_constraints", None)
    if truth is None:
        return None
    return _as_bool(truth(), "true_constraints()")


def false_positive_rate(learned, true) -> float | None:
    """|learned \\ true| / |learned|; 0 when nothing is learned; None when ``true`` is None
    (no ground truth: the rate does not apply)."""
    if true is None:
        return None
    learned, true = _same_shape_masks(learned, true)
    n = learned.sum()
    return float((learned & ~true).sum() / n) if n else 0.0


def false_negative_rate(learned, true) -> float | None:
    """|true \\ learned| / |true|; 0 when there is no true constraint; None when ``true``
    is None (no ground truth: the rate does not apply)."""
    if true is None:
        return None
    learned, true = _same_shape_masks(learned, true)
    n = true.sum()
    return float((true & ~learned).sum() / n) if n else 0.0


THRESHOLD_TOLERANCE = 1e-9  # far below any step, far above float64 rounding


def check_threshold(threshold) -> float:
    """The learned-constraint rule's ``threshold`` as a float in ``(0, 1]``: the weights
    ``ω_c`` live in ``[0, 1]``, so 0 would mark every feature; 1 marks those at the upper
    bound (``init_cost_weights=1`` starts there, and a weight stays there while each
    projected step clips to 1), a legitimate if strict rule.

    Raises:
        InvalidSetting: any other value.
    """
    return setting_number("threshold", threshold, low=0, high=1, low_open=True, example=0.5,
                          why="ω_c,j >= threshold marks a learned constraint")


def learned_constraints(cost_weights, threshold: float = 0.5) -> np.ndarray:
    """``ω_c,j >= threshold`` marks feature ``j`` as a learned constraint, up to
    ``THRESHOLD_TOLERANCE``: a clipped first LSCA step puts a weight at exactly
    β(0) = 0.5, and the consensus mix of equal values then rounds it to 0.4999999999999993
    (measured, MPE seed 1), which must not flip the decision."""
    threshold = check_threshold(threshold)
    w = np.asarray(cost_weights.cpu() if isinstance(cost_weights, torch.Tensor) else cost_weights)
    return w >= threshold - THRESHOLD_TOLERANCE


def reward_function_distance(weights, true_weights) -> float:
    """RFD = ‖ω_r − ω_rE‖ / ‖ω_rE‖."""
    w = np.asarray(weights, dtype=np.float64)
    w_e = np.asarray(true_weights, dtype=np.float64)
    if w.shape != w_e.shape:
        raise ValueError(f"weights {w.shape} and true weights {w_e.shape} differ in shape.")
    norm = np.linalg.norm(w_e)
    if norm == 0:
        raise ValueError("RFD is undefined for all-zero true weights.")
    return float(np.linalg.norm(w - w_e) / norm)


# A policy maps (t, cells [B, N] int64) to joint-action probabilities [B, A1**N].
Policy = Callable[[int, torch.Tensor], torch.Tensor]


@dataclass(frozen=True)
class RolloutResult:
    """Batched episodes in the true CMG.

    Attributes:
        returns: ``[B]`` total true reward of all experts.
        violated: ``[B, N]`` bool, expert violated a true constraint in the episode.
        cells: ``[B, T+1, N]`` visited cells (a frozen expert keeps its last cell).
        actions: ``[B, T, N]`` chosen actions.
    """

    returns: np.ndarray
    violated: np.ndarray
    cells: np.ndarray
    actions: np.ndarray

    @property
    def cr_mean(self) -> float:
        return float(self.returns.mean())

    @property
    def cr_std(self) -> float:
        return float(self.returns.std())

    @property
    def cvr(self) -> float:
        return float(self.violated.mean(1).mean())


def true_cmg_step(layout: GridLayout, cells: torch.Tensor, actions: torch.Tensor,
                  moved: torch.Tensor, active: torch.Tensor, next_cell: torch.Tensor,
                  constrained: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """One step for a batch, with the semantics of ``GridWorldCMG`` (tested against it).

    A forbidden action is a violation; in the true CMG (``constrained``) the expert then
    does not move. Otherwise it moves when ``moved``. Landing on an obstacle, or in the
    cell of another active expert, is a violation. Inactive (frozen) experts neither
    move nor collide.

    Args:
        cells, actions, moved, active: ``[B, N]``.
        next_cell: ``[S1, A1]`` successful-move targets.

    Returns:
        new cells ``[B, N]`` and this step's violations ``[B, N]`` (active experts only).
    """
    forbidden = torch.from_numpy(layout.forbidden_action_mask())[actions] & active
    go = moved & active & ~(forbidden & constrained)
    new = torch.where(go, next_cell[cells, actions], cells)
    violation = forbidden | (torch.from_numpy(layout.obstacle_mask())[new] & active)
    if layout.collision_constraint and cells.shape[1] > 1:
        same = (new.unsqueeze(2) == new.unsqueeze(1)) & active.unsqueeze(1) & active.unsqueeze(2)
        same &= ~torch.eye(cells.shape[1], dtype=torch.bool)
        violation |= same.any(2)
    return new, violation


def rollout_true_cmg(*, policy: Policy, model: TabularGridModel, layout: GridLayout,
                     reward_table: torch.Tensor, n_episodes: int,
                     rng: torch.Generator, constrained: bool = True) -> RolloutResult:
    """Roll a joint policy out in the true CMG (violators stop) or, with
    ``constrained=False``, in the nominal game (nobody stops; violations still count).

    Args:
        policy: ``(t, cells [B, N]) -> [B, A1**N]`` probabilities.
        model: the tabular model (dynamics, horizon, P0: each episode's start is drawn
            from it with ``rng`` before the first step).
        layout: the true constraints.
        reward_table: ``[N, S1]`` true reward of each expert in each cell.
        n_episodes: number of episodes ``B``.
        rng: a ``torch.Generator``.
    """
    if n_episodes < 1:
        raise ValueError(f"n_episodes must be >= 1, got {n_episodes}.")
    N, A1, T = model.n_experts, model.n_actions, model.horizon
    B = n_episodes
    # starts drawn from P0 with rng: nothing is drawn with fixed starts, so their stream
    # (and every result) is the one of a point-mass P0
    cells = model.sample_starts(B, rng)
    active = torch.ones(B, N, dtype=torch.bool)
    violated = torch.zeros(B, N, dtype=torch.bool)
    returns = torch.zeros(B, dtype=torch.float64)
    all_cells = torch.empty(B, T + 1, N, dtype=torch.int64)
    all_actions = torch.empty(B, T, N, dtype=torch.int64)
    all_cells[:, 0] = cells
    expert_idx = torch.arange(N)
    for t in range(T):
        returns += (reward_table[expert_idx, cells].double() * active).sum(1)
        joint = torch.multinomial(policy(t, cells).double().cpu(), 1, generator=rng).squeeze(1)
        actions = decode_joint(joint, A1, N)
        moved = torch.rand(B, N, generator=rng, dtype=torch.float64) < model.p_success
        cells, violation = true_cmg_step(layout, cells, actions, moved, active, model.next_cell,
                                         constrained)
        violated |= violation
        if constrained:
            active &= ~violation
        all_cells[:, t + 1], all_actions[:, t] = cells, actions
    return RolloutResult(returns=returns.numpy(), violated=violated.numpy(),
                         cells=all_cells.numpy(), actions=all_actions.numpy())
