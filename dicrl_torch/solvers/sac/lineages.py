"""Training a SAC solver in scored chunks and keeping the best: :class:`LineageTraining`
(the solver's :meth:`solve_keeping_best`, :meth:`train_lineages`, :meth:`adopt_best`) and
the :class:`Lineage` it returns.

SAC's iterates can swing between behaviours from one chunk to the next; these methods
keep the best chunk seen, over one or several lineages (clones of the solver that then
diverge), which a run may split over processes (docs/design.md §7, the shared warm-up).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import torch

from dicrl_torch.solvers.sac.checks import _is_int
from dicrl_torch.solvers.sac.solution import SACSolution

__all__ = ["Lineage", "LineageTraining", "step_bar"]


@dataclass
class Lineage:
    """One lineage of :meth:`SACConstrainedSolver.train_lineages`: its best chunk.

    Attributes:
        restart: the lineage's index (0: the solver itself).
        key: the chunk's rank ``(success, penalised return, -restart, -chunk)``; the
            highest is adopted.
        checks: every chunk's ``{"restart", "timesteps", "penalised_return",
            "success_under_constraints"}``.
        policy_state: the SB3 policy's ``state_dict`` after the best chunk.
        solution: that chunk's :class:`SACSolution` (None when read back from a file).
    """

    restart: int
    key: tuple[float, float, int, int]
    checks: list[dict]
    policy_state: dict[str, torch.Tensor]
    solution: SACSolution | None = None

    def state(self) -> dict[str, Any]:
        """Tensors and plain values only (for ``torch.save`` and a ``weights_only``
        load); the solution stays behind."""
        return {"restart": self.restart, "key": list(self.key), "checks": self.checks,
                "policy_state": self.policy_state}

    @classmethod
    def from_state(cls, state: dict[str, Any]) -> Lineage:
        """The lineage of :meth:`state` (without its solution)."""
        s, objective, r, k = state["key"]
        return cls(restart=int(state["restart"]), key=(float(s), float(objective), int(r),
                                                        int(k)),
                   checks=list(state["checks"]), policy_state=dict(state["policy_state"]))


class LineageTraining:
    """The chunked, best-keeping training of
    :class:`~dicrl_torch.solvers.sac.SACConstrainedSolver` (a mixin of it: it uses the
    solver's ``_train``, ``evaluate``, ``clone``, ``policy_state``, ``seed`` and
    ``replay_buffer``)."""

    def solve_keeping_best(self, eta: Any, cost_weights: Any, timesteps: int, *, checks: int,
                           restarts: int = 1, n_eval_episodes: int | None = None,
                           deterministic: bool = False, constraints: Any = None,
                           penalty_basis: Any = None, stop_at: float | None = None,
                           progress: str | None = None) -> SACSolution:
        """Train ``timesteps`` in ``checks`` near-equal chunks and end with the networks
        whose policy scored the highest learned objective
        (:meth:`SACSolution.penalised_return`) after any chunk; with ``constraints``, the
        highest :meth:`SACSolution.success_rate_under` them first (ties: the objective).

        SAC's iterates can swing between behaviours from one chunk to the next (seen in
        the paper's continuous experiment; the Table 2 notes in docs/); this keeps the
        best one seen, as an evaluation callback that saves the best model does. With
        ``restarts`` > 1 the same is done from this solver's current state by
        ``restarts - 1`` clones as well (:meth:`clone`, seeds drawn from this
        solver's), whose lineages diverge, and the best chunk of any of them is kept: more
        independent chances when one lineage never settles. The score is the learner's
        own: its ``(η, ω_c)``, rolled out in the solver's game (the nominal one by default);
        no true constraint is consulted.

        Args:
            eta, cost_weights, n_eval_episodes: as :meth:`solve` (rollouts per score).
            timesteps: env steps per restart (>= ``checks``).
            checks: number of chunks per restart, each followed by a score; 1 (with one
                restart) is :meth:`solve`.
            restarts: independent continuations from the current state (1: this solver's).
            deterministic: score the mean-action policy (how it is deployed).
            constraints: ``[l_c]`` bool, the learner's constraint set (e.g. its
                ``ω_c ≥ 0.5``), or None.
            penalty_basis: train on the penalty ``λ ω_c · φ`` with ``φ`` this basis's
                features (``l_c`` of them, e.g. the cost basis grown by a margin:
                ``CellOccupancyCostBasis.dilated``) for this solve only
                (:meth:`FeatureReplayBuffer.set_penalty_basis`); the scores and the
                returned estimates keep the cost basis. None: the cost basis.
            stop_at: a lineage ends at its first chunk whose success under
                ``constraints`` reaches this (no later chunk can score a higher success;
                the steps left are not trained), or None: every chunk is trained.
            progress: a tqdm bar over every lineage's env steps with this label (the
                best score so far beside it), or None.

        Returns:
            The best chunk's :class:`SACSolution` (its rollouts gave the score); this
            solver's networks are left as that chunk's. Every chunk's ``{"restart",
            "timesteps", "penalised_return", "success_under_constraints"}`` (the last None
            without ``constraints``) is left in ``self.last_checks``.
        """
        lineages = self.train_lineages(
            eta, cost_weights, timesteps, checks=checks, restarts=restarts,
            n_eval_episodes=n_eval_episodes, deterministic=deterministic,
            constraints=constraints, penalty_basis=penalty_basis, stop_at=stop_at,
            progress=progress)
        # A clone's solution: its policy now lives here (the clone is closed).
        return replace(self.adopt_best(lineages).solution, solver=self)

    def train_lineages(self, eta: Any, cost_weights: Any, timesteps: int, *, checks: int,
                       restarts: int = 1, lineages: Sequence[int] | None = None,
                       n_eval_episodes: int | None = None, deterministic: bool = False,
                       constraints: Any = None, penalty_basis: Any = None,
                       stop_at: float | None = None, progress: str | None = None
                       ) -> list[Lineage]:
        """:meth:`solve_keeping_best`'s lineages ``lineages`` (default every one of
        ``range(restarts)``), each trained and scored chunk by chunk, without adopting
        any: :meth:`adopt_best` does that. Lineage 0 is this solver itself (trained
        last, so that the clones start from its current state), lineage ``r > 0`` the
        clone seeded by the ``r``-th seed drawn from this solver's seed.

        As every lineage depends only on the solver's state and its own seed, equal
        solvers in several processes can each train a share of them: :meth:`adopt_best`
        of all the lineages (read back with :meth:`Lineage.from_state`), in the process
        that trained lineage 0, leaves that solver as one :meth:`solve_keeping_best`
        would have (docs/design.md §7, the shared warm-up).

        Args: as :meth:`solve_keeping_best`; ``progress`` counts the steps of the
        lineages trained here.

        Returns:
            One :class:`Lineage` per lineage trained, in increasing order.
        """
        if not _is_int(checks) or checks < 1:
            raise ValueError(f"checks must be a positive int, got {checks!r}.")
        if not _is_int(timesteps) or timesteps < checks:
            raise ValueError(f"timesteps must be an int >= checks={checks}, got "
                             f"{timesteps!r}.")
        if not _is_int(restarts) or restarts < 1:
            raise ValueError(f"restarts must be a positive int, got {restarts!r}.")
        if stop_at is not None and (constraints is None or isinstance(stop_at, bool)
                                    or not isinstance(stop_at, int | float)
                                    or not 0.0 < stop_at <= 1.0):
            raise ValueError(f"stop_at must be a success rate in (0, 1] scored under "
                             f"constraints (given), or None; got stop_at={stop_at!r}, "
                             f"constraints={'None' if constraints is None else 'given'}.")
        mine = list(range(restarts)) if lineages is None else [int(r) for r in lineages]
        if not mine or sorted(set(mine)) != sorted(mine) or min(mine) < 0 \
                or max(mine) >= restarts:
            raise ValueError(f"lineages must be distinct ints in [0, restarts={restarts}), "
                             f"got {lineages!r}.")
        chunks = np.diff(np.linspace(0, int(timesteps), checks + 1).round().astype(int))
        # Clone seeds come from this solver's seed, so a run is reproducible. The clones
        # run first, one at a time (each holds a copy of the replay buffer), while this
        # solver still has the state they start from; it runs last as restart 0.
        seeds = np.random.SeedSequence([self.seed, 4]).generate_state(restarts - 1)
        order = [r for r in sorted(mine) if r] + [0] * (0 in mine)
        # Set before the clones copy the buffer; every later solve trains on φ_c again.
        self.replay_buffer.set_penalty_basis(penalty_basis)
        try:
            with step_bar(progress, len(order) * int(timesteps)) as bar:
                done = [self._lineage(r, seeds, eta, cost_weights, chunks, n_eval_episodes,
                                      deterministic, constraints, stop_at, bar)
                        for r in order]
        finally:
            self.replay_buffer.set_penalty_basis(None)
        return sorted(done, key=lambda lineage: lineage.restart)

    def _lineage(self, r: int, seeds: np.ndarray, eta: Any, cost_weights: Any,
                 chunks: np.ndarray, n_eval_episodes: int | None, deterministic: bool,
                 constraints: Any, stop_at: float | None, bar: Any) -> Lineage:
        """Lineage ``r`` of :meth:`train_lineages` (0: this solver, else a clone of
        ``seeds[r - 1]``): its best chunk and every chunk's scores."""
        solver = self if r == 0 else self.clone(int(seeds[r - 1]))
        best = None
        checks = []
        for k, steps in enumerate(chunks):
            solver._train(eta, cost_weights, int(steps), bar)
            solution = solver.evaluate(n_eval_episodes, deterministic=deterministic)
            objective = solution.penalised_return()[0]
            success = (None if constraints is None
                       else solution.success_rate_under(constraints))
            checks.append({"restart": r, "timesteps": solver.num_timesteps,
                           "penalised_return": objective,
                           "success_under_constraints": success})
            # Ties go to the earlier restart, then the earlier chunk.
            key = (0.0 if success is None else success, objective, -r, -k)
            if best is None or key > best.key:
                best = Lineage(restart=r, key=key, checks=checks, solution=solution,
                               policy_state=solver.policy_state())
            if bar is not None:  # the best so far: its success rate, its objective
                bar.set_postfix(lineage=r, best_objective=f"{best.key[1]:.1f}",
                                **({} if success is None
                                   else {"best_success": f"{best.key[0]:.2f}"}),
                                refresh=False)
            if stop_at is not None and success >= stop_at:
                if bar is not None:  # the steps not trained: the bar ends at its total
                    bar.update(int(chunks[k + 1:].sum()))
                break
        if solver is not self:
            solver.close()
        return best

    def adopt_best(self, lineages: Sequence[Lineage]) -> Lineage:
        """Load the policy of the best-scored chunk of ``lineages`` (every lineage of a
        :meth:`train_lineages` split, see there) into this solver, leave every chunk's
        scores in ``self.last_checks`` (by restart, then chunk) and return that lineage."""
        if not lineages or len({lineage.restart for lineage in lineages}) != len(lineages):
            raise ValueError(f"adopt_best needs distinct lineages, got restarts "
                             f"{[lineage.restart for lineage in lineages]}.")
        best = max(lineages, key=lambda lineage: lineage.key)
        self.load_policy_state(best.policy_state)
        self.last_checks = [c for lineage in sorted(lineages, key=lambda x: x.restart)
                            for c in lineage.checks]
        return best


# ---- progress ---------------------------------------------------------------------
@contextlib.contextmanager
def step_bar(label: str | None, total: int) -> Iterator[Any]:
    """A tqdm bar of ``total`` env steps labelled ``label`` (closed on exit), or None
    without a label."""
    if label is None:
        yield None
        return
    from tqdm.auto import tqdm

    bar = tqdm(total=int(total), desc=label, unit="step", leave=False)
    try:
        yield bar
    finally:
        bar.close()
