"""The inner processes (``dicrl_torch.algos.inner``) against C-ICRL's on the pooled
shards, C-ICRL stepping as a run steps it (``TrainerSpec``: ᾱ / N_L, the network average of
Algorithm 2's steps): tracking keeps every learner on that iterate, Algorithm 2 only their
mean."""

from __future__ import annotations

import numpy as np
import pytest
import tiny_dicrl
import torch

from dicrl_torch.algos.dicrl import DICRL, StepSizes
from dicrl_torch.comm import (
    CompleteSchedule,
    MatrixSchedule,
    SimulatedCommunicator,
    TimeVaryingSchedule,
)
from dicrl_torch.demos.storage import Demonstrations
from dicrl_torch.runs.runner import TrainerSpec


@pytest.fixture(scope="module")
def tiny():
    return tiny_dicrl.build_tiny()


def run_steps(n_learners: int) -> StepSizes:
    """A run's step sizes for a trainer of ``n_learners`` (C-ICRL: 1) when the distributed
    learners step with the tiny trainer's ᾱ = 0.02."""
    spec = TrainerSpec(schedules=lambda n: (CompleteSchedule(n_learners=n),) * 2,
                       steps=StepSizes(alpha_bar=0.02), inner_step=0.01,
                       n_shards=len(tiny_dicrl.SPLIT))
    return spec.kwargs(n_learners)["steps"]


def c_icrl(tiny, inner_method: str = "paper", inner_steps: int = 3,
           steps: StepSizes | None = None) -> DICRL:
    """C-ICRL: one learner holding every shard, the tiny trainer's settings but ``steps``
    (default: the tiny trainer's ᾱ, unscaled)."""
    solver, rb, cb, shards = tiny
    pooled = Demonstrations(states=np.concatenate([s.states for s in shards]),
                            actions=np.concatenate([s.actions for s in shards]),
                            n_cells=shards[0].n_cells, n_actions=shards[0].n_actions)
    return DICRL(solver=solver, reward_basis=rb, cost_basis=cb, shards=[pooled],
                 trajectory_counts=[sum(tiny_dicrl.SPLIT)],
                 communicator=SimulatedCommunicator(1),
                 inner_schedule=CompleteSchedule(n_learners=1),
                 outer_schedule=CompleteSchedule(n_learners=1), init_cost_weights=0.3,
                 steps=steps or StepSizes(alpha_bar=0.02), inner_steps=inner_steps,
                 lsca_curvature=10.0, inner_method=inner_method)


def relative_gap(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).abs().max() / b.abs().max())


def test_tracking_on_a_complete_graph_is_c_icrl_on_the_pooled_shards(tiny):
    """Every learner's η̄ after the first inner process is C-ICRL's as a run steps it (to
    rounding); under Algorithm 2 each learner also moves by its own shard's step, and its
    η̄ is apart from it."""
    c = c_icrl(tiny, steps=run_steps(1))
    c.train(1)
    n = len(tiny_dicrl.SPLIT)
    rows = {}
    for method in ("tracking", "paper"):
        d = tiny_dicrl.make_trainer(tiny, inner=CompleteSchedule(n_learners=n),
                                    inner_method=method, init_cost=0.3)
        d.train(1)
        rows[method] = d.state.eta_bar
    want = c.state.eta_bar.expand(n, -1)
    assert relative_gap(rows["tracking"], want) < 1e-12
    assert relative_gap(rows["paper"], want) > 1e-2


def test_both_methods_step_the_network_as_c_icrl_and_tracking_keeps_it_together(tiny):
    """One step (K = 2) over the time-varying graph, where no W(0) connects the learners:
    under either method their mean η̄ is C-ICRL's as a run steps it (W doubly stochastic,
    C-ICRL's ᾱ / N_L), and a run's C-ICRL at the learners' own ᾱ would step N_L times
    further. Tracking's learners step on the mixed gradients, so they stay closer to that
    mean than Algorithm 2's, which step on their own shard's."""
    c = c_icrl(tiny, inner_steps=2, steps=run_steps(1))
    c.train(1)
    c_unscaled = c_icrl(tiny, inner_steps=2)
    c_unscaled.train(1)
    spread = {}
    for method in ("tracking", "paper"):
        d = tiny_dicrl.make_trainer(tiny, inner_method=method, init_cost=0.3, inner_steps=2)
        d.train(1)
        mean = d.state.eta_bar.mean(0, keepdim=True)
        assert relative_gap(mean, c.state.eta_bar) < 1e-12, method
        assert relative_gap(mean, c_unscaled.state.eta_bar) > 1e-2, method
        spread[method] = float((d.state.eta_bar - mean).abs().max())
    assert 0 < spread["tracking"] < 0.75 * spread["paper"]


def test_a_network_of_one_runs_algorithm_2_bit_for_bit(tiny):
    paper, tracking = c_icrl(tiny), c_icrl(tiny, inner_method="tracking")
    paper.train(2)
    tracking.train(2)
    for key in ("eta", "eta_bar", "cost_weights"):
        assert torch.equal(getattr(paper.state, key), getattr(tracking.state, key))


def test_tracking_combines_each_step_over_a_window_of_the_period(tiny):
    """On a period-2 graph (no round connects the 3 learners) tracking's step k mixes
    rounds 2k and 2k+1: the same η̄ and ω_c as tracking over the schedule of window
    products W(2k+1) W(2k) (period 1)."""
    n = len(tiny_dicrl.SPLIT)
    graph = TimeVaryingSchedule(n_learners=n, period=2)
    products = MatrixSchedule([graph(2 * k + 1) @ graph(2 * k) for k in range(2)], period=1)
    def connected(W):  # positive diagonal: strongly connected iff W^(n-1) > 0
        return bool((torch.linalg.matrix_power((W > 0).double(), n - 1) > 0).all())
    assert not connected(graph(0)) and not connected(graph(1)) and connected(products(0))
    runs = {}
    for name, schedule in (("window", graph), ("products", products)):
        d = tiny_dicrl.make_trainer(tiny, inner=schedule, inner_method="tracking",
                                    init_cost=0.3)
        d.train(2)
        runs[name] = d
    for key in ("eta_bar", "eta", "cost_weights"):
        a, b = getattr(runs["window"].state, key), getattr(runs["products"].state, key)
        assert relative_gap(a, b) < 1e-12, key
    assert relative_gap(runs["window"].state.eta_bar,
                        runs["window"].state.eta_bar.mean(0)) > 1e-3  # still apart


def test_shard_fits_are_each_learner_alone_from_its_trained_state(tiny):
    """``shard_fits`` is, for each learner, a network of one holding its shard alone
    (Algorithm 2 with W = I, the learners' own ᾱ) run from its trained η̄ and ω_c; the
    trainer's state is left as it was."""
    solver, rb, cb, shards = tiny
    d = tiny_dicrl.make_trainer(tiny, inner_method="tracking", init_cost=0.3)
    d.train(2)
    before = {k: getattr(d.state, k).clone() for k in ("eta", "eta_bar", "cost_weights")}
    fits = d.shard_fits()
    for k, v in before.items():
        assert torch.equal(getattr(d.state, k), v), k
    for i, (shard, m) in enumerate(zip(shards, tiny_dicrl.SPLIT, strict=True)):
        alone = DICRL(solver=solver, reward_basis=rb, cost_basis=cb, shards=[shard],
                      trajectory_counts=[m], communicator=SimulatedCommunicator(1),
                      inner_schedule=CompleteSchedule(n_learners=1),
                      outer_schedule=CompleteSchedule(n_learners=1),
                      steps=StepSizes(alpha_bar=0.02), inner_steps=3, lsca_curvature=10.0)
        want, _ = alone.inner_process(d.state.cost_weights[i], d.state.eta_bar[i:i + 1])
        assert relative_gap(fits[i:i + 1], want) < 1e-12, i
    assert relative_gap(fits, d.state.eta_bar) > 1e-3  # the shards pull them apart


def test_c_icrl_fits_on_its_folds_are_the_learners_fits_from_its_reward(tiny):
    """C-ICRL (one learner pooling the shards, stepping at ᾱ / N_L as a run does) asked for
    fits on the shards gives, for each, the fit that shard's learner makes from the same
    η̄ and ω_c; the C-ICRL trainer's state is left as it was. A network's trainer is
    refused folds (its learners fit their own shards)."""
    solver, rb, cb, shards = tiny
    c = c_icrl(tiny, steps=run_steps(1))
    c.train(2)
    before = {k: getattr(c.state, k).clone() for k in ("eta", "eta_bar", "cost_weights")}
    fits = c.shard_fits(folds=shards)
    for k, v in before.items():
        assert torch.equal(getattr(c.state, k), v), k
    n = len(tiny_dicrl.SPLIT)
    d = tiny_dicrl.make_trainer(tiny, inner_method="tracking")
    d.state.eta_bar = c.state.eta_bar.expand(n, -1).clone()
    d.state.cost_weights = c.state.cost_weights.expand(n, -1).clone()
    want = d.shard_fits()
    assert fits.shape == want.shape == (n, rb.dim + 1)
    assert relative_gap(fits, want) < 1e-12
    assert relative_gap(fits, c.state.eta_bar.expand(n, -1)) > 1e-3  # the folds pull apart
    with pytest.raises(ValueError, match="one learner holding every shard"):
        d.shard_fits(folds=shards)
