"""Exact finite-horizon soft-Bellman solver on the factored grid-world model (docs/design.md §4).

Backward pass, for t = T-1 .. 0 (``V_T = 0``)::

    Q_t(s, a) = Σ_i r_i(s_i, a_i) + g(s) + γ E[V_{t+1}(s') | s, a]
    V_t(s)    = logsumexp_a Q_t(s, a),        π_t(a|s) = exp(Q_t(s, a) - V_t(s))

The joint transition is a product of per-expert "move or stay" operators, so
``E[V(s')]`` is computed by applying expert ``i``'s operator along axis ``i`` of ``V``.
Because an operator's probabilities sum to one, a reward term that does not depend on
``s_i`` passes through it unchanged; hence we apply the operators of experts N..2,
adding ``r_i`` after each (arrays of ``S·A^(N-1)`` entries), and fuse the last operator
with the logsumexp over all actions. Only that last fused stage touches all
``S·A`` pairs; it is chunked over expert 1's cell (eager) or compiled into one
vectorised loop nest by ``torch.compile`` so the ``S·A`` array is never materialised.

Tensor layout: *actions first*, ``[a_1, .., a_k, s_1, .., s_N]``, so every reduction
and gather runs over contiguous state memory.

*Scale.* ``V_t`` holds about ``T - t`` steps of reward, mostly a constant over states
that the policy does not see; float32 would resolve the policy only to ``|V_t| · 6e-8``.
The values are therefore kept about a per-step baseline, ``V_t = v_t + c_t`` with
``c_t`` a float64 scalar (``SoftBellmanSolution.values`` and ``.baseline``): the
constant passes through every operator, so each step computes at the scale of the spread
of ``V_t`` over states (:func:`.backward.backward_pass`).

Forward pass: the state occupancy is pushed through the transposed operators. A push
is a scatter; we write it as a *pull* over a small predecessor table of each expert
(``pred[a, s', k]``: the cells that reach ``s'`` under ``a``, with their probabilities),
which compiles to plain gathers. Per-expert state-action marginals fall out of the
partial contractions; feature expectations are contracted from them, never from a
per-step ``S·A`` array.

Hard constraints are ``-inf`` rewards; a temperature ``τ`` is a reward scaling
(``V = τ logsumexp(Q/τ)``) and ``τ = 0`` gives the hard-max DP.

**Two backups.** ``solve(..., backup="causal")`` (default) is the maximum-*causal*-entropy
model above. ``backup="trajectory"`` is the (trajectory-level) maximum-entropy model of
Ziebart et al. (2008), ``P(ζ) ∝ P0(s_0) Π_t P(s_{t+1}|s_t, a_t) exp(Σ_t r(s_t, a_t))``,
whose backward recursion replaces the expected next value by its log-expected-exp::

    L_t(s, a) = log E[exp V_{t+1}(s') | s, a],    Q_t = r + γ L_t,    V_t = logsumexp_a Q_t

computed through the same per-expert operators in log space: each operator combines
its two outcomes (move, stay) with a ``logaddexp``, i.e. each element subtracts its own
max, so nothing overflows or underflows to a wrong value in float32. Rewards pass
through (``log E[exp(X + c)] = c + log E[exp X]`` for ``c`` constant along the mixed
axis), divided by ``γ`` so that the final ``γ ·`` gives them back unscaled.

*Discounting.* ``γ`` multiplies the continuation ``L_t`` exactly where it multiplies
``E[V_{t+1}]`` in the causal backup. At ``γ = 1`` this is Ziebart's model exactly; for
any ``γ`` and deterministic dynamics, ``L_t = V_{t+1}(s')`` and both backups coincide.
For ``γ < 1`` it is the exact solution of the variational problem
``max E_{π, P̃}[Σ_t γ^t (r_t + H(π_t(·|s_t))) − Σ_t γ^{t+1} KL(P̃_t(·|s_t, a_t) ‖ P)]``:
the model also picks the *dynamics* ``P̃`` (this is how the trajectory-level model
differs from the causal one), paying for departing from ``P`` at the discount of the
state it arrives in. Its optimum is ``π_t = exp(Q_t − V_t)`` and the optimistic,
tilted dynamics ``P̃_t(s'|s, a) = P(s'|s, a) exp(V_{t+1}(s') − L_t(s, a))``, with
``P̃_0(s) ∝ P0(s) exp V_0(s)``. (Putting ``γ`` inside, ``log E[exp γV]``, would charge
the KL at ``γ^t``; the exact Gibbs law of the discounted return needs a time-varying
temperature ``γ^{-t}`` and would not coincide with the causal backup for deterministic
dynamics.) The γ-discounted log-likelihood of a trajectory then telescopes to
``Σ_t γ^t r(s_t, a_t) + γ^T V_T(s_T) − log Σ_s P0(s) exp V_0(s)`` (+ terms of ``P``
and ``P0`` that do not depend on the model); see ``dicrl_torch.algos.greedy``.

The trajectory forward pass pushes ``ρ_t = d_t π_t`` through the tilted dynamics. The
tilt ``exp(V_{t+1}(s') − L_t(s, a))`` is split over the experts along the chain of
partial log-expectations ``Λ`` the backward pass builds (``Λ_N = V_{t+1}``, ``Λ_{i-1} =
log E_i[exp Λ_i]``, ``Λ_0 = L_t``): expert ``i``'s factor ``P_i exp(Λ_i − Λ_{i-1})`` is a
proper transition kernel whose weights are at most ``1/min(p, 1-p)``, so each push stays
mass-preserving and bounded, and the per-expert marginals are read off exactly as in
the causal pass.

Modules: :mod:`.operators` (the per-expert operators), :mod:`.backward` (values),
:mod:`.forward` (occupancies), :mod:`.solution` (:class:`SoftBellmanSolution`) and
:mod:`.solver` (:class:`FactoredSoftBellman`, which puts them together).
"""

from dicrl_torch.solvers.factored.solution import SoftBellmanSolution
from dicrl_torch.solvers.factored.solver import (
    COMPILE_MIN_PAIRS,
    FLOAT32_VALUE_LIMIT,
    FactoredSoftBellman,
)

__all__ = ["COMPILE_MIN_PAIRS", "FLOAT32_VALUE_LIMIT", "FactoredSoftBellman",
           "SoftBellmanSolution"]
