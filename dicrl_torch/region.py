"""Recovered constraints scored as regions of the state space, whatever the basis.

FPR and FNR compare learned *features* with the features a hand-made basis marks as true;
they say nothing for a basis with no such marks (a neural one) and little about how much
of the forbidden space a learned set covers. Here the learned set is scored as a
classifier of joint states instead (docs/design.md §6, "Regions"):

- the game says which joint states are forbidden, geometrically (:class:`RegionTruth`:
  e.g. an agent inside the MPE disc, two agents closer than the minimum distance);
- a dense test set samples the reachable joint states uniformly (positions over the
  arena, velocities in the disc of the game's top speed), seeded;
- a state is predicted forbidden when the learned cost on the learned set is positive
  there (budget 0: the constraint set of feature ``j`` is its support ``{φ_j > 0}``,
  paper §3), i.e. when some learned feature is positive;
- a free state that no demonstration speaks about is *undetermined*, not false: an
  agent's position farther than the demonstrations' own step from every demonstrated
  position, or a separation below the smallest the demonstrations show
  (:func:`undetermined_states`; the band comes from the demonstrations, never from the
  truth). Precision is stated both ways.

:func:`recall_bound` says before training how much of the forbidden region a basis can
express for a learner: the share covered by the supports of the features its
demonstrations never use (start-state features excluded: the trainer pins them to 0).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

__all__ = ["RegionTruth", "feature_support", "predicted_forbidden", "recall_bound",
           "region_scores", "undetermined_states"]

POSITIONS, VELOCITIES = slice(0, 2), slice(2, 4)
"""Where a joint state ``[..., N, 4]`` of the built-in continuous games keeps each agent's
position and velocity."""
_CHUNK = 4096  # test states per feature call: bounded memory for any basis width


@dataclass(frozen=True)
class RegionTruth:
    """A game's forbidden joint states as a function, and its reachable ones to sample.

    Attributes:
        forbidden: joint states ``[M, N, 4]`` float64 ``(x, y, vx, vy)`` per agent ->
            ``[M]`` bool, the states a true constraint forbids (every agent active).
        low, high: ``(x, y)`` corners of the box an agent can reach.
        max_speed: an agent's top speed; test velocities are uniform in the disc of this
            radius.
        n_agents: ``N``.
        kinds: what ``forbidden`` counts, for messages and docs (e.g. ``"disc"``,
            ``"proximity"``).
    """

    forbidden: Callable[[np.ndarray], np.ndarray]
    low: tuple[float, float]
    high: tuple[float, float]
    max_speed: float
    n_agents: int
    kinds: tuple[str, ...] = ()

    def test_states(self, n: int, seed: int = 0) -> np.ndarray:
        """``n`` joint states ``[n, N, 4]`` float64 drawn uniformly from the reachable
        ones: each agent's position in the box, its velocity in the top-speed disc."""
        rng = np.random.default_rng([int(seed), 52])
        pos = rng.uniform(self.low, self.high, size=(n, self.n_agents, 2))
        angle = rng.uniform(0.0, 2 * np.pi, size=(n, self.n_agents))
        speed = self.max_speed * np.sqrt(rng.uniform(0.0, 1.0, size=(n, self.n_agents)))
        vel = np.stack([speed * np.cos(angle), speed * np.sin(angle)], -1)
        return np.concatenate([pos, vel], -1)


def feature_support(basis: Any, states: np.ndarray) -> np.ndarray:
    """``[M, l]`` bool: where each feature of ``basis`` is positive on joint states
    ``[M, N, d_s]`` (in chunks, through the basis's checked ``forward``)."""
    out = []
    with torch.no_grad():
        for k in range(0, len(states), _CHUNK):
            phi = basis(torch.from_numpy(np.ascontiguousarray(states[k:k + _CHUNK])))
            out.append(phi.cpu().numpy() > 0)
    return np.concatenate(out) if out else np.zeros((0, basis.dim), dtype=bool)


def predicted_forbidden(support: np.ndarray, learned: Any) -> np.ndarray:
    """``[M]`` bool: the states where the learned cost on the learned set is positive,
    from :func:`feature_support` ``[M, l]`` and the learned set ``[l]`` bool (its
    weights are ≥ the threshold > 0, so the cost is positive where a learned feature
    is)."""
    learned = np.asarray(learned, dtype=bool)
    if learned.shape != (support.shape[1],):
        raise ValueError(f"learned must be a [{support.shape[1]}] bool mask, got shape "
                         f"{learned.shape}.")
    return support[:, learned].any(-1)


def _pairwise_min(pos: np.ndarray) -> np.ndarray:
    """``[...]`` the smallest distance between two agents of positions ``[..., N, 2]``
    (inf with one agent)."""
    n = pos.shape[-2]
    if n < 2:
        return np.full(pos.shape[:-2], np.inf)
    d = np.linalg.norm(pos[..., :, None, :] - pos[..., None, :, :], axis=-1)
    d[..., np.arange(n), np.arange(n)] = np.inf
    return d.min((-1, -2))


def _nearest_distance(points: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """``[P]`` distance from each of ``points`` ``[P, 2]`` to the nearest of
    ``reference`` ``[R, 2]`` (chunked)."""
    ref = torch.from_numpy(np.ascontiguousarray(reference, dtype=np.float64))
    out = []
    for k in range(0, len(points), _CHUNK):
        p = torch.from_numpy(np.ascontiguousarray(points[k:k + _CHUNK], dtype=np.float64))
        out.append(torch.cdist(p, ref).amin(1).numpy())
    return np.concatenate(out) if out else np.zeros(0)


def undetermined_states(test_states: np.ndarray, free: np.ndarray,
                        episodes: Sequence[np.ndarray]) -> tuple[np.ndarray, dict]:
    """Which free test states no demonstration speaks about, from the demonstrations
    alone.

    A free state is undetermined when some agent's position lies farther than ``step``
    from every demonstrated position of any agent (``step``: the longest move of an agent
    between two consecutive demonstrated states, the demonstrations' own resolution), or
    when two agents are closer than the smallest separation the demonstrations show.

    Args:
        test_states: ``[M, N, d_s]`` joint states (positions in columns 0-1).
        free: ``[M]`` bool, the states no true constraint forbids.
        episodes: each demonstration's joint states ``[T_k, N, d_s]``.

    Returns:
        ``[M]`` bool, and the band's ``{"step", "min_separation"}``.
    """
    if not len(episodes):
        raise ValueError("undetermined_states needs at least one demonstration.")
    positions = np.concatenate([e[..., POSITIONS].reshape(-1, 2) for e in episodes])
    step = max(float(np.linalg.norm(np.diff(e[..., POSITIONS], axis=0), axis=-1).max(
        initial=0.0)) for e in episodes)
    separation = min(float(_pairwise_min(e[..., POSITIONS]).min(initial=np.inf))
                     for e in episodes)
    pos = test_states[..., POSITIONS]
    m, n = pos.shape[:2]
    far = (_nearest_distance(pos.reshape(-1, 2), positions).reshape(m, n) > step).any(-1)
    close = _pairwise_min(pos) < separation
    return np.asarray(free, dtype=bool) & (far | close), {"step": step,
                                                          "min_separation": separation}


def region_scores(forbidden: np.ndarray, predicted: np.ndarray,
                  undetermined: np.ndarray) -> dict[str, float]:
    """The learned set as a classifier of the test states.

    Args:
        forbidden, predicted, undetermined: ``[M]`` bool (the truth, the learned set's
            verdict, the free states no demonstration speaks about).

    Returns:
        ``recall`` (share of forbidden states predicted; 1 with none forbidden),
        ``precision`` (share of predicted states that are forbidden; 1 with none
        predicted), ``precision_determined`` (the same with undetermined states set
        apart), ``iou`` (intersection over union; 1 when both are empty),
        ``undetermined`` (share of predicted states that are undetermined; 0 with none).
    """
    f, p, u = (np.asarray(x, dtype=bool) for x in (forbidden, predicted, undetermined))
    if not f.shape == p.shape == u.shape or f.ndim != 1:
        raise ValueError(f"forbidden, predicted and undetermined must be [M] bool masks of "
                         f"one length, got shapes {f.shape}, {p.shape}, {u.shape}.")
    if (u & f).any():
        raise ValueError("undetermined states must be free (not forbidden).")
    tp, n_pred, n_forb = int((p & f).sum()), int(p.sum()), int(f.sum())
    determined = int((p & (f | ~u)).sum())
    union = int((p | f).sum())
    return {"recall": tp / n_forb if n_forb else 1.0,
            "precision": tp / n_pred if n_pred else 1.0,
            "precision_determined": tp / determined if determined else 1.0,
            "iou": tp / union if union else 1.0,
            "undetermined": int((p & u).sum()) / n_pred if n_pred else 0.0}


def recall_bound(support: np.ndarray, forbidden: np.ndarray, usable: np.ndarray) -> float:
    """The most of the forbidden region a learner can recover with a basis: the share of
    forbidden test states inside the support of some feature it can learn at all.

    Args:
        support: :func:`feature_support` of the test states ``[M, l]``.
        forbidden: ``[M]`` bool.
        usable: ``[l]`` bool, the features that can become constraints: positive on none
            of the learner's demonstrated states (a feature its experts make positive is
            no constraint of theirs) and none of the start states (the trainer pins
            those to 0).
    """
    f = np.asarray(forbidden, dtype=bool)
    if not f.any():
        return 1.0
    return float(support[f][:, np.asarray(usable, dtype=bool)].any(-1).mean())
