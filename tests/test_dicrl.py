"""D-ICRL trainer mechanics on a tiny instance: determinism, consensus, C-ICRL, the
inner-process merge, input checks before any computation, and the privacy audit."""

from __future__ import annotations

import numpy as np
import pytest
import tiny_dicrl
import torch

from dicrl_torch.algos.callbacks import InnerScalars, TrainerCallback
from dicrl_torch.algos.dicrl import DICRL, StepSizes
from dicrl_torch.algos.models import TabularLearnerModel
from dicrl_torch.checks import InvalidSetting
from dicrl_torch.comm import (
    ALLOWED_FIELDS,
    CompleteSchedule,
    DirectedCycleSchedule,
    GraphAssumptionError,
    MatrixSchedule,
    RingSchedule,
    SimulatedCommunicator,
    TimeVaryingSchedule,
)

SPLIT = tiny_dicrl.SPLIT


@pytest.fixture(scope="module")
def setup():
    return tiny_dicrl.build_tiny()


def make(setup, *, record=False, **kw):
    return tiny_dicrl.make_trainer(
        setup, communicator=SimulatedCommunicator(len(SPLIT), record=record), **kw)


def test_same_seed_same_numbers_and_consensus(setup):
    a, b = make(setup), make(setup)
    a.train(3)
    b.train(3)
    assert torch.equal(a.state.cost_weights, b.state.cost_weights)
    assert torch.equal(a.state.eta_bar, b.state.eta_bar)
    # a complete outer graph averages ω_c exactly: all learners agree after a step
    assert a.disagreement() == 0.0
    assert ((a.state.cost_weights >= 0) & (a.state.cost_weights <= 1)).all()
    # distinct initial ω_c: distinct inner processes, and their warm starts stay distinct
    assert [h["inner_processes"] for h in a.history] == [3, 3, 3]


def test_disagreement_of_eta_is_the_pairwise_distance_that_the_inner_graph_leaves(setup):
    """ω_c: the complete outer graph averages exactly; η̄: only the inner graph mixes it,
    so a directed cycle (slow mixing, K = 3 steps) leaves the learners apart, and a
    complete inner graph less so."""
    n = len(SPLIT)
    gaps = {}
    for name, inner in (("cycle", DirectedCycleSchedule(n_learners=n)),
                        ("complete", CompleteSchedule(n_learners=n))):
        t = make(setup, inner=inner)
        t.train(2)
        eta = t.state.eta_bar
        brute = max(float(torch.linalg.vector_norm(eta[a] - eta[b]))
                    for a in range(n) for b in range(n))
        assert t.disagreement("eta") == pytest.approx(brute, rel=1e-12)
        assert t.disagreement("cost_weights") == 0.0
        gaps[name] = brute
    assert gaps["cycle"] > 0 and gaps["complete"] < gaps["cycle"]
    with pytest.raises(ValueError, match="field must be one of"):
        t.disagreement("eta_bar")


def test_merging_identical_inner_processes_changes_nothing(setup):
    # a common start: one inner process serves all learners, bit for bit
    merged = make(setup, init_cost=0.3)
    separate = make(setup, init_cost=0.3, merge_identical_inner=False)
    merged.train(3)
    separate.train(3)
    assert [h["inner_processes"] for h in merged.history] == [1, 1, 1]
    assert torch.equal(merged.state.cost_weights, separate.state.cost_weights)
    assert torch.equal(merged.state.eta_bar, separate.state.eta_bar)
    assert torch.equal(merged.state.tracker, separate.state.tracker)
    assert merged.solves < separate.solves


class _StatefulTabularModel(TabularLearnerModel):
    """The exact tabular model flagged stateful (as SAC's): its numbers do not depend on
    its (empty) state, so merged and unmerged runs must agree."""

    stateful = True

    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, sd: dict) -> None:
        pass


def test_a_stateful_model_runs_one_inner_process_per_equal_cost_only_when_asked(setup):
    """With equal ω_c (a complete outer graph), Algorithm 1's N_L inner processes are one
    problem: merged, each learner solves K - 1 times per process and once for its LGA
    (C-ICRL's count), with the numbers of the exact solver's merged run; unmerged (the
    default for a stateful model), every learner solves in all N_L processes."""
    solver, rb, cb, _ = setup
    n, K, outer = len(SPLIT), 3, 3
    runs = {}
    for merge in (False, True):
        model = _StatefulTabularModel(solver=solver, reward_basis=rb, cost_basis=cb)
        runs[merge] = make(setup, init_cost=0.3, learner_model=model,
                           merge_stateful_inner=merge)
        runs[merge].train(outer)
    assert [h["inner_processes"] for h in runs[False].history] == [n] * outer
    assert [h["inner_processes"] for h in runs[True].history] == [1] * outer
    assert runs[False].solves == outer * n * (n * (K - 1) + 1)
    assert runs[True].solves == outer * n * ((K - 1) + 1)
    exact = make(setup, init_cost=0.3)  # stateless: merged by default, bit-identical
    exact.train(outer)
    for field in ("cost_weights", "eta_bar", "tracker"):
        assert torch.equal(getattr(runs[True].state, field), getattr(exact.state, field))
        assert torch.equal(getattr(runs[False].state, field), getattr(exact.state, field))
    # the two settings train a real stateful model differently: one refuses the other's
    with pytest.raises(ValueError, match="differently configured trainer"):
        runs[False].load_state_dict(runs[True].state_dict())
    with pytest.raises(InvalidSetting, match="merge_stateful_inner"):
        make(setup, merge_stateful_inner="yes")


def test_c_icrl_is_one_learner(setup):
    solver, rb, cb, shards = setup
    from dicrl_torch.demos.storage import Demonstrations

    pooled = Demonstrations(states=np.concatenate([s.states for s in shards]),
                            actions=np.concatenate([s.actions for s in shards]),
                            n_cells=shards[0].n_cells, n_actions=shards[0].n_actions)
    c = DICRL(solver=solver, reward_basis=rb, cost_basis=cb, shards=[pooled],
              trajectory_counts=[pooled.n_trajectories],
              communicator=SimulatedCommunicator(1),
              inner_schedule=CompleteSchedule(n_learners=1),
              outer_schedule=CompleteSchedule(n_learners=1), inner_steps=3)
    c.train(2)
    assert c.state.cost_weights.shape == (1, cb.dim)
    assert torch.isfinite(c.state.eta_bar).all()


def test_the_lga_raises_unvisited_features_and_lambda_falls(setup):
    t = make(setup, init_cost=0.3)
    t.train(4)
    cw = t.state.cost_weights[0]
    accrued = torch.stack([s.cost_accrual > 0 for s in t.stats]).any(0)
    # features no demonstration accrues end up above those they all accrue
    assert cw[~accrued].mean() > cw[accrued].mean()
    assert t.state.eta_bar[0, -1] < -1.0  # the penalty multiplier grows


def test_privacy_audit_only_documented_fields(setup):
    t = make(setup, record=True)
    t.train(2)
    d, p = t.learner_model.cost_dim, t.learner_model.reward_dim + 1
    sizes = {"eta": (p,), "cost_weights": (d,), "tracker": (d,), "inner_tracker": (p,)}
    assert t.comm.messages
    for msg in t.comm.messages:
        assert msg.field in ALLOWED_FIELDS
        assert msg.shape == sizes[msg.field]
    with pytest.raises(ValueError, match="may not leave"):
        t.comm.all_gather(torch.zeros(3, d), "cost_accrual")


def test_bad_configurations_are_refused_before_computing(setup):
    solver, rb, cb, shards = setup
    with pytest.raises(GraphAssumptionError, match="Assumption 3"):
        make(setup, inner=None, **{}).__class__(
            solver=solver, reward_basis=rb, cost_basis=cb, shards=shards,
            trajectory_counts=SPLIT, communicator=SimulatedCommunicator(3),
            inner_schedule=RingSchedule(n_learners=3),
            outer_schedule=TimeVaryingSchedule(n_learners=3, period=2))
    with pytest.raises(GraphAssumptionError, match="Assumption 1"):
        make(setup, inner=MatrixSchedule([np.eye(3)]))
    with pytest.raises(ValueError, match="trajectory_counts"):
        DICRL(solver=solver, reward_basis=rb, cost_basis=cb, shards=shards,
              trajectory_counts=[3, 3, 4], communicator=SimulatedCommunicator(3),
              inner_schedule=RingSchedule(n_learners=3),
              outer_schedule=CompleteSchedule(n_learners=3))
    with pytest.raises(ValueError, match="shards"):
        DICRL(solver=solver, reward_basis=rb, cost_basis=cb, shards=shards[:2],
              trajectory_counts=SPLIT, communicator=SimulatedCommunicator(3),
              inner_schedule=RingSchedule(n_learners=3),
              outer_schedule=CompleteSchedule(n_learners=3))
    with pytest.raises(ValueError, match="beta_power"):
        StepSizes(beta_power=0.4)
    with pytest.raises(ValueError, match="beta_bar"):
        StepSizes(beta_bar=1.5)
    with pytest.raises(ValueError, match="alpha_bar"):
        StepSizes(alpha_bar=-1.0)
    with pytest.raises(ValueError, match="multiplier_scale"):
        StepSizes(multiplier_scale=0.0)


def test_multiplier_scale_scales_only_the_multiplier_step(setup):
    """One inner step (K = 2) from the same η: with ``multiplier_scale = 3`` the ω_r
    coordinates move exactly as with 1 and λ moves exactly 3 times as far from the
    consensus point."""
    paper = make(setup, inner_steps=2)
    scaled = make(setup, inner_steps=2,
                  steps=StepSizes(alpha_bar=0.02, multiplier_scale=3.0))
    cost = torch.full(paper.state.cost_weights.shape[1:], 0.3, dtype=torch.float64)
    eta0 = torch.randn(paper.state.eta_bar.shape, generator=torch.Generator().manual_seed(0),
                       dtype=torch.float64)
    _, eta_paper = paper.inner_process(cost, eta0)
    _, eta_scaled = scaled.inner_process(cost, eta0)
    mixed = paper.comm.mix(eta0, paper.inner_schedule(0), "eta")
    torch.testing.assert_close(eta_scaled[:, :-1], eta_paper[:, :-1], rtol=0, atol=0)
    assert torch.all((eta_paper[:, -1] - mixed[:, -1]).abs() > 1e-6)
    torch.testing.assert_close(eta_scaled[:, -1] - mixed[:, -1],
                               3.0 * (eta_paper[:, -1] - mixed[:, -1]), rtol=1e-12, atol=0)


@pytest.mark.parametrize("d", [5, 52, 53, 130])
def test_network_or_is_the_or_of_every_learners_mask_in_52_bit_words(setup, d):
    """The OR over learners of a feature mask, packed 52 bits to a float64 word: equal to
    the dense OR for widths around a word's edge, and counted as ⌈d/52⌉ words to each of
    the other learners."""
    trainer = make(setup)
    n = len(SPLIT)
    masks = torch.rand(n, d, generator=torch.Generator().manual_seed(d)) < 0.1
    masks[n - 1, d - 1] = True  # the last bit of the last word
    before = trainer.comm.traffic.report(0)["sent"]["outer"]["bytes"]
    assert torch.equal(trainer.network_or(masks), masks.any(0))
    sent = trainer.comm.traffic.report(0)["sent"]["outer"]["bytes"] - before
    assert sent == (n - 1) * 8 * -(-d // 52)
    with pytest.raises(ValueError, match="one row per local learner"):
        trainer.network_or(masks[:1])


def test_pruning_bounds_the_likelihood_of_the_whole_pruned_set(setup):
    """Backward elimination: the kept set explains the data to within ``min_gain`` of the
    trained set, and each kept constraint is needed (dropping it too breaks that bound).
    Dropping every individually redundant constraint at once would break it here."""
    from dicrl_torch.algos.icrl import log_likelihood, model_reward

    t = make(setup, init_cost=0.6)
    t.train(2)
    trained = t.state.cost_weights[0].clone()
    learned = torch.nonzero(trained >= 0.5).flatten().tolist()
    assert len(learned) > 2
    assert t.prune_constraints(0, min_gain=-float("inf"))[1] == []
    assert sorted(t.prune_constraints(0, min_gain=float("inf"))[1]) == learned
    eta, demos = t.state.eta_bar[0], t.shards[0]

    def ll(w):  # independent of the trainer's likelihood path
        lm = t.learner_model
        sol = lm.solver.solve(model_reward(lm.fr, lm.fc, eta[:-1], float(eta[-1]), w),
                              forward=False)
        return log_likelihood(sol, demos) / demos.n_trajectories

    def without(w, js):
        w = w.clone()
        w[js] = 0.0
        return w

    gain = 0.6  # 8 of the 13 constraints are redundant alone, not together
    base = ll(trained)
    alone = [j for j in learned if base - ll(without(trained, [j])) < gain]
    assert len(alone) >= 2 and base - ll(without(trained, alone)) >= gain

    kept, pruned = t.prune_constraints(0, min_gain=gain)
    assert pruned and set(pruned) <= set(learned)
    torch.testing.assert_close(kept, without(trained, pruned), rtol=0, atol=0)
    assert base - ll(kept) < gain
    for j in set(learned) - set(pruned):
        assert base - ll(without(kept, [j])) >= gain
    assert torch.equal(t.state.cost_weights[0], trained)  # the trainer's state is untouched


def test_gradient_tracking_inner_variant_converges_faster(setup):
    from dicrl_torch.algos.icrl import dual_gradient

    cw = torch.full((setup[2].dim,), 0.3, dtype=torch.float64)

    def residual(**kw):
        t = make(setup, init_cost=0.3, **kw)
        t.K = 20
        bar, _ = t.inner_process(cw, t.state.eta[0])
        return float(torch.stack([t.m[i] * dual_gradient(t.solve(i, bar[i], cw), st, cw)
                                  for i, st in enumerate(t.stats)]).sum(0).norm())

    paper = residual()
    tracking = residual(inner_method="gradient_tracking", inner_step=0.02)
    assert tracking < 0.5 * paper  # measured: 10.7 vs 42.3 at K = 20
    with pytest.raises(ValueError, match="inner_method"):
        make(setup, inner_method="newton")


def test_inner_scalars_are_logged_per_learner(setup):
    class Recorder:
        def __init__(self):
            self.rows = []

        def scalar(self, run, tag, value, step):
            self.rows.append((run, tag, step))

    rec = Recorder()
    t = make(setup, callbacks=[InnerScalars(rec, lambda v: f"learner{v}")])
    t.train(2)
    runs = {r for r, _, _ in rec.rows}
    assert runs == {"learner0", "learner1", "learner2"}
    tags = {tag for _, tag, _ in rec.rows}
    assert tags == {"inner/dual_gradient_norm", "inner/multiplier", "inner/reward_weight_norm"}
    # each learner logs its own inner process once per inner gradient: K-1 per outer step
    steps = sorted(s for r, tag, s in rec.rows if r == "learner0" and "dual" in tag)
    assert steps == [0, 1, 3, 4]


def test_features_with_p0_mass_keep_zero_cost_weight_at_every_outer_iteration(setup):
    """The start cells (P0's support) can never be constraints with budget 0: ω_c holds 0
    there from ω_c(0) on, through every step and consensus, whatever the initial ω_c
    elsewhere (here 0.2-0.4, without pruning the features the demonstrations accrue)."""
    t = make(setup)
    names = setup[2].names
    assert {names[j] for j in torch.nonzero(t.pinned).flatten()} == {"cell(0,2)", "cell(2,0)"}
    seen = []

    class Check(TrainerCallback):
        def on_outer_end(self, trainer, info):
            seen.append(trainer.state.cost_weights.clone())

    # ω_c(0): 0 at the start cells, the given 0.2 / 0.3 / 0.4 everywhere else
    start = t.state.cost_weights.clone()
    assert (start[:, t.pinned] == 0).all()
    assert torch.allclose(start[:, ~t.pinned], torch.tensor([[0.2], [0.3], [0.4]],
                                                            dtype=torch.float64))
    t.train(4, callbacks=[Check()])
    assert len(seen) == 4
    for cw in seen:
        assert (cw[:, t.pinned] == 0).all()
