"""The inner processes of D-ICRL: Algorithm 2 and two variants that track the network's
average gradient (docs/design.md §5).

For one cost vector ω_c every learner ``v`` runs, from its warm start ``η^[v](0)``,
``K - 1`` steps on its dual gradient ``g^[v] = m^[v] ∇G^[v](η^[v]; ω_c)`` (``m^[v]`` its
trajectory count, so ``Σ_v g^[v]`` is the gradient on the pooled demonstrations that
C-ICRL steps on), mixing over the inner graph ``W(k)``:

- ``"paper"`` (Algorithm 2): ``η ← W η − α(k) g``, ``α(k) = ᾱ / (k + 1)``, output the
  α-weighted average ``η̄ = Σ_k α(k) η(k) / Σ_k α(k)``. Mixing moves the learners'
  average by the mean of their steps, ``α(k) Σ_v g^[v] / N_L``, which is C-ICRL's step as
  a run sets it (one learner with every trajectory at ``ᾱ / N_L``: ``TrainerSpec``). Each
  learner's own iterate, though, moves by its own shard's step ``α(k) g^[v]``: where the
  shards' gradients disagree (varied starts) the learners scatter round that mean, and
  each one's η̄ averages its own iterates.
- ``"tracking"``: the same steps, schedule and average, but adapt-then-combine with a
  tracker ``s`` of the average gradient::

      η ← W_k (η − α(k) s),   s ← W_k (s + g(η_new) − g(η_old)),   s(0) = g(η(0))

  where ``W_k = W(Bk + B − 1) ⋯ W(Bk)`` mixes over a window of the inner graph's period
  ``B`` (``B`` exchanges a step; ``W_k = W(k)`` on a graph connected at every round). On
  a time-varying graph no single round connects the learners, and a step combined over
  one round leaves an isolated learner stepping on its own gradient alone.

  The trackers' mean is the gradients' mean at every step (W doubly stochastic), so the
  network takes Algorithm 2's step, C-ICRL's; every learner steps on the mixed estimate of
  the average gradient instead of its own. On a complete uniform W every learner's η is
  C-ICRL's iterate on the pooled shards (tested), on a sparser W it is that up to the
  consensus error. A network of one runs Algorithm 2 itself (the same numbers, bit for
  bit, where the tracker would round ``s + g_new - g``).
- ``"gradient_tracking"`` (DIGing): ``η ← W η − inner_step · s``,
  ``s ← W s + g(η_new) − g(η_old)``, a constant step; the output is the final η.
"""

from __future__ import annotations

import torch


class InnerProcesses:
    """The inner process of :class:`~dicrl_torch.algos.dicrl.DICRL` (a mixin: it reads the
    trainer's ``inner_method``, ``inner_step``, ``K``, ``steps``, ``n_learners``, ``comm``
    and its gradient, graph and finiteness helpers)."""

    def inner_process(self, cost_weights: torch.Tensor, eta0: torch.Tensor
                      ) -> tuple[torch.Tensor, torch.Tensor]:
        """The inner process for one ω_c ``[d]``: ``eta0`` ``[n, p]`` -> (η̄ ``[n, p]``,
        final η ``[n, p]``) of the local learners."""
        if self.inner_method == "gradient_tracking":
            return self._inner_gradient_tracking(cost_weights, eta0)
        if self.inner_method == "tracking" and self.n_learners > 1:
            return self._alpha_average(self._tracking_iterates(cost_weights, eta0))
        return self._alpha_average(self._paper_iterates(cost_weights, eta0))

    def _alpha_average(self, iterates) -> tuple[torch.Tensor, torch.Tensor]:
        """Algorithm 2's output from the iterates η(0), ..., η(K-1) ``[n, p]``: their
        α(k)-weighted average η̄ and the last."""
        acc, alpha_sum = None, 0.0
        for k, eta in enumerate(iterates):
            a = self.steps.alpha(k)
            acc = (torch.zeros_like(eta) if acc is None else acc) + a * eta
            alpha_sum += a
        return acc / alpha_sum, eta

    def shard_fits(self, folds=None) -> torch.Tensor:
        """Each local learner's inner process on its own shard alone, from its trained η̄
        and ω_c: Algorithm 2 with no neighbours (``W = I``), ``K - 1`` steps of
        ``α(k) m^[v] ∇G^[v]`` and their α-weighted average, ``[n, p]``. Where the shards
        disagree, these rewards differ as the learners' own data pull them; nothing is
        exchanged and the trainer's state is unchanged.

        ``folds``: for a trainer of one learner holding the pooled shards (C-ICRL), those
        shards: the fit each shard's learner would make from this learner's η̄ and ω_c,
        ``[len(folds), p]``. The pooled trainer steps at ``ᾱ / N_L`` (the runner's
        ``TrainerSpec``), so a fold ``f`` of ``m_f`` trajectories steps ``N_L`` times that
        on ``m_f ∇G_f``: its learner's own step. A tabular model only (the fits solve for
        ``len(folds)`` learners the trainer does not hold)."""
        if folds is None:
            return self._alpha_average(self._paper_iterates(
                self.state.cost_weights, self.state.eta_bar, mix=False))[0]
        if self.n_learners != 1 or getattr(self.learner_model, "stateful", False):
            raise ValueError("Fits on folds are for one learner holding every shard (C-ICRL) "
                             "of a stateless (tabular) model; a network's learners fit their "
                             "own shards: call shard_fits() without folds.")
        stats = [self.learner_model.statistics(f) for f in folds]
        m = torch.tensor([float(st.m) for st in stats], dtype=torch.float64) * len(folds)
        eta0 = self.state.eta_bar.expand(len(folds), -1).clone()
        return self._alpha_average(self._paper_iterates(
            self.state.cost_weights[0], eta0, mix=False, stats=stats, m=m))[0]

    def _gradients(self, eta: torch.Tensor, cost_weights: torch.Tensor, k: int,
                   **fold_data) -> torch.Tensor:
        grads = self._scaled_gradients(eta, cost_weights, k, **fold_data)
        self._check_finite("The dual gradient m ∇G", grads, k, self._process)
        return grads

    def _paper_iterates(self, cost_weights, eta0, mix: bool = True, **fold_data):
        """Algorithm 2's iterates; ``mix=False``: each learner alone (``W = I``, nothing
        sent); ``cost_weights`` ``[d]`` or ``[n, d]``; ``fold_data``: ``stats`` and ``m`` in
        place of the learners' (:meth:`shard_fits` on folds)."""
        eta = eta0.clone()
        for k in range(self.K - 1):
            yield eta
            grads = self._gradients(eta, cost_weights, k, **fold_data)
            if mix:
                eta = self.comm.mix(eta, self._inner_matrix(k), "eta")
            eta = eta - self.steps.alpha(k) * grads
            self._check_finite("η = [ω_r, λ]", eta, k, self._process)
        yield eta

    def _mix_window(self, values: torch.Tensor, k: int, field: str) -> torch.Tensor:
        """Step ``k``'s mixing over the rounds ``Bk, ..., Bk + B - 1`` of the inner graph
        (``B`` its period), one exchange each: their product is strongly connected
        (Assumption 1), so every step's combination reaches every learner."""
        period = self.inner_schedule.period
        for r in range(period * k, period * (k + 1)):
            values = self.comm.mix(values, self._inner_matrix(r), field)
        return values

    def _tracking_iterates(self, cost_weights, eta0):
        eta = eta0.clone()
        g = s = self._gradients(eta, cost_weights, 0)
        for k in range(self.K - 1):
            yield eta
            eta = self._mix_window(eta - self.steps.alpha(k) * s, k, "eta")
            self._check_finite("η = [ω_r, λ]", eta, k, self._process)
            if k < self.K - 2:  # the last iterate needs no gradient
                g_new = self._gradients(eta, cost_weights, k + 1)
                s = self._mix_window(s + g_new - g, k, "inner_tracker")
                self._check_finite("The inner gradient tracker", s, k + 1, self._process)
                g = g_new
        yield eta

    def _inner_gradient_tracking(self, cost_weights, eta0):
        eta = eta0.clone()
        g = s = self._gradients(eta, cost_weights, 0)
        for k in range(self.K - 1):
            W = self._inner_matrix(k)
            eta = self.comm.mix(eta, W, "eta") - self.inner_step * s
            self._check_finite("η = [ω_r, λ]", eta, k, self._process)
            if k == self.K - 2:
                break
            g_new = self._gradients(eta, cost_weights, k + 1)
            s = self.comm.mix(s, W, "inner_tracker") + g_new - g
            self._check_finite("The inner gradient tracker", s, k + 1, self._process)
            g = g_new
        return eta, eta
