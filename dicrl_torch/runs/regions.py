"""Region scores and expressivity for the continuous tasks: :class:`RegionScoring`, a
mixin of :class:`~dicrl_torch.runs.continuous.SACTask` (docs/design.md §6.1).

A game that knows its forbidden joint states (:meth:`RegionScoring.region_truth`) gets
every learned set scored as a classifier of states, each learner told before training how
much of the forbidden region its cost basis can express, a basis that can express nothing
refused, and a map of each learned set beside the truth.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from typing import Any

import numpy as np

from dicrl_torch.envs.parallel import figure_image
from dicrl_torch.region import (
    RegionTruth,
    feature_support,
    predicted_forbidden,
    recall_bound,
    region_scores,
    undetermined_states,
)

__all__ = ["RegionScoring", "region_map"]


def _episodes(demos: Any) -> list[np.ndarray]:
    """Each demonstration's joint states ``[T_k + 1, N, d_s]``, without the padding past
    its end."""
    return [demos.states[k, :int(demos.lengths[k]) + 1] for k in range(len(demos.lengths))]


class RegionScoring:
    """The region machinery of a continuous task (a mixin: it uses the task's
    ``cost_basis``, ``demos``, ``shards``, ``start_states``, ``seed`` and
    ``learned_mask``)."""

    region_test_states: int = 20_000
    """Joint states in the region scores' test set (:mod:`dicrl_torch.region`)."""
    REGION_KEYS = ("region_recall", "region_precision", "region_precision_determined",
                   "region_iou", "region_undetermined")

    def region_truth(self) -> RegionTruth | None:
        """The game's forbidden joint states (:class:`~dicrl_torch.region.RegionTruth`);
        None here: a game of unknown truth, whose region scores are ``null``."""
        return None

    def region_test(self) -> dict[str, Any] | None:
        """The region scores' test set, computed once: ``states`` ``[M, N, d_s]``,
        ``forbidden`` and ``undetermined`` ``[M]`` bool, ``support`` ``[M, l_c]`` bool
        (where each cost feature is positive) and the demonstrations' ``band``; None
        without a :meth:`region_truth`."""
        if not hasattr(self, "_region_test"):
            truth = self.region_truth()
            if truth is None:
                self._region_test = None
            else:
                states = truth.test_states(self.region_test_states, seed=self.seed)
                forbidden = np.asarray(truth.forbidden(states), dtype=bool)
                undetermined, band = undetermined_states(states, ~forbidden,
                                                         _episodes(self.demos))
                self._region_test = {"states": states, "forbidden": forbidden,
                                     "undetermined": undetermined, "band": band,
                                     "support": feature_support(self.cost_basis, states),
                                     "kinds": truth.kinds}
        return self._region_test

    def constrainable(self) -> np.ndarray:
        """``[n_shards + 1, l_c]`` bool: per learner (the shards, then C-ICRL holding them
        all) the cost features that can become constraints at all: positive on none of
        its demonstrated states and none of the start states (budget 0: a feature its
        experts make positive is no constraint of theirs, and the trainer pins the start
        states' features to 0)."""
        if not hasattr(self, "_constrainable"):
            start = feature_support(self.cost_basis, np.asarray(self.start_states)).any(0) \
                if self.start_states is not None else np.zeros(self.cost_basis.dim, bool)
            rows = []
            for d in (*self.shards, self.demos):
                states = np.concatenate(_episodes(d))
                rows.append(~(feature_support(self.cost_basis, states).any(0) | start))
            self._constrainable = np.stack(rows)
        return self._constrainable

    def check_expressive(self) -> None:
        """Refuse a cost basis of which no learner can learn any constraint (every
        feature positive on its demonstrations or the start states: e.g. a network
        ending in a sigmoid, positive everywhere), naming the fix, before training."""
        if not self.constrainable().any():
            raise ValueError(
                f"The cost basis {getattr(self.cost_basis, 'label', type(self.cost_basis))} "
                f"can express no constraint: every one of its {self.cost_basis.dim} "
                f"features is positive on every learner's demonstrations or on the start "
                f"states, and with budget 0 a feature's constraint set is where it is "
                f"positive (paper §3), so none can be learned (a network ending in a "
                f"sigmoid is positive everywhere). Use features with exact zeros: e.g. "
                f"features/cost=local_relu (LocalReLUBasis), or end your network with a "
                f"ReLU clipped to max_value (torch.clamp(x, 0, max_value)) so that each "
                f"feature is 0 outside a region.")

    def expressivity(self) -> list[float] | None:
        """Per learner (the shards in order, then C-ICRL holding them all), the most of
        the forbidden region its learned set can cover with this cost basis
        (:func:`~dicrl_torch.region.recall_bound`: the share of forbidden test states in
        the support of a feature that neither its demonstrations nor the start states
        make positive); None without a :meth:`region_truth`. Computed from the shards and
        the basis alone, before training."""
        test = self.region_test()
        if test is None:
            return None
        return [recall_bound(test["support"], test["forbidden"], usable)
                for usable in self.constrainable()]

    def region_rates(self, mask: np.ndarray) -> dict[str, float | None]:
        """The learned set ``mask`` ``[l_c]`` bool scored as a classifier of the test
        states (:func:`~dicrl_torch.region.region_scores`, keys ``region_*``); every
        value None without a :meth:`region_truth`."""
        test = self.region_test()
        if test is None:
            return dict.fromkeys(self.REGION_KEYS)
        scores = region_scores(test["forbidden"], predicted_forbidden(test["support"], mask),
                               test["undetermined"])
        return {f"region_{k}": v for k, v in scores.items()}

    def print_expressivity(self) -> None:
        """One line: each learner's :meth:`expressivity` (nothing without a truth)."""
        bounds = self.expressivity()
        if bounds is not None:
            print("the most of the forbidden region each learned set can cover with this "
                  "cost basis (an upper bound on region recall): "
                  + ", ".join(f"learner {v + 1} {b:.2f}" for v, b in enumerate(bounds[:-1]))
                  + f", C-ICRL {bounds[-1]:.2f}", flush=True)

    def _bound(self, trainer: Any, i: int) -> float | None:
        """The :meth:`expressivity` of ``trainer``'s local learner ``i`` (C-ICRL: all
        the demonstrations)."""
        bounds = self.expressivity()
        if bounds is None:
            return None
        return bounds[-1] if trainer.n_learners == 1 else bounds[trainer.local[i]]

    def region_maps(self, methods: dict, experiment: str) -> dict[str, np.ndarray]:
        """Per learned row ``region_<method>_<v>``: over the positions an agent can
        reach, the share of the region test set's states with an agent there that the
        learned set forbids, beside the share the truth forbids (the region itself, plus
        the pairwise part spread thin); none without a :meth:`region_truth`."""
        test = self.region_test()
        if test is None:
            return {}
        truth = self.region_truth()
        images = {}
        for name, m in methods.items():
            for v, row in enumerate(m["learners"]):
                if row.get("constraints") is None:
                    continue
                predicted = predicted_forbidden(test["support"], self.learned_mask(row))
                tag = "region_" + re.sub(r"[^\w.-]", "", name) + f"_{v + 1}"
                images[tag] = region_map(
                    test["states"], predicted, test["forbidden"], truth.low, truth.high,
                    title=f"{experiment}, {name} {v + 1}: forbidden share by position "
                          f"(R_rec {row.get('region_recall', 0):.2f}, "
                          f"R_prec {row.get('region_precision', 0):.2f})")
        return images


def region_map(states: np.ndarray, predicted: np.ndarray, forbidden: np.ndarray,
               low: Sequence[float], high: Sequence[float], *, title: str = "",
               bins: int = 30) -> np.ndarray:
    """Two panels over an agent's positions ``(x, y)`` in the box ``low``-``high``: the
    share of joint states ``[M, N, d_s]`` with an agent in each bin that ``predicted``
    ``[M]`` marks (the learned set), and that ``forbidden`` ``[M]`` marks (the truth);
    an ``H x W x 3`` uint8 image."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    pos = states[..., :2].reshape(-1, 2)
    n = states.shape[1]
    edges = [np.linspace(low[k], high[k], bins + 1) for k in range(2)]
    count, _, _ = np.histogram2d(pos[:, 0], pos[:, 1], bins=edges)
    fig = Figure(figsize=(7.0, 3.6), dpi=80)
    FigureCanvasAgg(fig)
    for k, (mask, label) in enumerate(((predicted, "learned set"), (forbidden, "truth"))):
        hit, _, _ = np.histogram2d(pos[:, 0], pos[:, 1], bins=edges,
                                   weights=np.repeat(np.asarray(mask, float), n))
        ax = fig.add_subplot(1, 2, k + 1)
        image = ax.imshow((hit / np.maximum(count, 1)).T, origin="lower", vmin=0, vmax=1,
                          extent=(low[0], high[0], low[1], high[1]), cmap="Reds")
        ax.set_title(label, fontsize=8)
        ax.set_aspect("equal")
    fig.colorbar(image, ax=fig.axes, shrink=0.8, label="share of states forbidden")
    fig.suptitle(title, fontsize=8)
    return figure_image(fig)
