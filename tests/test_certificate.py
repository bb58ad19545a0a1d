"""The learners' constraint certificate (``certify_constraints``, docs/design.md §6) on tiny
layouts whose answers are derived by hand, and its use as the grid rows' constraint rule."""

from __future__ import annotations

import json

import pytest
import torch
from test_identifiability import demos_of, names, one_expert, problem, thick_wall
from tiny_train import compose_train, finished_run

from dicrl_torch.algos.identifiability import certify_constraints, classify_features
from dicrl_torch.envs.grid import GridLayout
from dicrl_torch.features.bases import GoalClosenessRewardBasis, SharedIndicatorCostBasis

pytestmark = pytest.mark.filterwarnings("ignore:Sparse invariant checks:UserWarning")


def test_the_certificate_with_the_true_reward_finds_the_hand_derived_required_cells():
    """thick_wall (test_identifiability): (1,1) and (2,1) are shortcuts with probability 1;
    (1,0) and (2,0) are never entered. The certificate knows only the demonstrations and a
    reward: given the true one it certifies exactly the two shortcuts."""
    model, solver, reward, demos = thick_wall()
    basis = SharedIndicatorCostBasis(model)
    cert = certify_constraints(solver=solver, reward=reward, cost_basis=basis,
                               demonstrations=demos)
    assert names(cert, cert.required) == {"cell(1,1)", "cell(2,1)"}
    assert cert.temperature == 0.0 and cert.min_probability == pytest.approx(1e-3)


def test_the_certificate_is_invariant_to_the_reward_scale():
    """At temperature 0 the policy is the hard max with uniform ties: scaling the learned
    reward (which optimal demonstrations let grow without bound) changes nothing."""
    model, solver, _, demos = thick_wall()
    basis = SharedIndicatorCostBasis(model)
    rb = GoalClosenessRewardBasis(model)
    results = [certify_constraints(solver=solver, reward=rb().weighted(rb.true_weights() * c),
                                   cost_basis=basis, demonstrations=demos)
               for c in (1.0, 7.5)]
    assert torch.equal(results[0].required, results[1].required)
    both = torch.isfinite(results[0].probability)
    assert torch.allclose(results[0].probability[both], results[1].probability[both])


def tied_routes():
    """3x3, one expert from (0,1) to (2,1) round the obstacle (1,1), T = 4, deterministic::

        . a .     two tied routes of 2 moves: NE (1,0) SE, or SE (1,2) NE; then stay
        S # G     shard A took the first only, shard B the second
        . b .

    Shard A alone leaves (1,2) unseen, and with everything else it never saw forbidden,
    the optimal expert with (1,2) open takes it half the time (the two first moves tie):
    a 10-trajectory shard misses a 1/2 route with probability 2^-10, and across many
    learners and seeds one does. Shard B's demonstrations show the route."""
    layout = GridLayout(size=3, starts=((0, 1),), goals=((2, 1),), obstacles=((1, 1),))
    model, solver, reward = problem(layout, horizon=4)
    shard_a = demos_of(model, one_expert("NE SE stay stay"))
    shard_b = demos_of(model, one_expert("SE NE stay stay"))
    return model, solver, reward, shard_a, shard_b


def test_a_route_another_shard_shows_is_not_certified():
    """Own shard only: (1,2) certified with probability exactly 1/2 (hand-derived above).
    With the features another learner's shard accrues (``also_demonstrated``, the bitmask
    the learners exchange): not a candidate, and the rest of the set is unchanged."""
    from dicrl_torch.algos.identifiability import demonstrated_mask

    model, solver, reward, shard_a, shard_b = tied_routes()
    basis = SharedIndicatorCostBasis(model)
    j = basis.names.index("cell(1,2)")
    own = certify_constraints(solver=solver, reward=reward, cost_basis=basis,
                              demonstrations=shard_a)
    assert float(own.probability[j]) == pytest.approx(0.5, abs=1e-12)
    assert "cell(1,2)" in names(own, own.required)
    others = demonstrated_mask(cost_basis=basis, model=model, demonstrations=shard_b)
    assert bool(others[j]) and not bool(others[basis.names.index("cell(1,0)")])
    network = certify_constraints(solver=solver, reward=reward, cost_basis=basis,
                                  demonstrations=shard_a, also_demonstrated=others)
    assert "cell(1,2)" not in names(network, network.required)
    assert bool(network.demonstrated[j]) and torch.isnan(network.probability[j])
    assert names(network, network.required) == names(own, own.required) - {"cell(1,2)"}
    # the pooled shards are the same question asked of all the demonstrations at once
    pooled = certify_constraints(solver=solver, reward=reward, cost_basis=basis,
                                 demonstrations=[shard_a, shard_b])
    assert torch.equal(pooled.required, network.required)


def test_a_route_only_one_reward_ranks_first_is_not_certified():
    """tied_routes with shard A alone: a reward that pays a little for (1,2) makes the
    route through it the only optimal one (probability 1); one that pays for (1,0) makes
    the demonstrated route the only one (probability 0). Certified under the first alone;
    with the second among ``other_rewards`` not (the data rank neither route first);
    with the true reward (a tie) beside it, certified at the smaller probability, 1/2."""
    from dicrl_torch.features.bases import FactoredReward

    model, solver, reward, shard_a, _ = tied_routes()
    basis = SharedIndicatorCostBasis(model)
    j = basis.names.index("cell(1,2)")

    def paying(cell):
        local = reward.local.clone()
        local[0, cell[1] * 3 + cell[0], :] += 0.01
        return FactoredReward(local=local)

    prefers_b, prefers_a = paying((1, 2)), paying((1, 0))

    def certified(r, others=()):
        cert = certify_constraints(solver=solver, reward=r, cost_basis=basis,
                                   demonstrations=shard_a, other_rewards=others)
        return "cell(1,2)" in names(cert, cert.required), float(cert.probability[j])

    assert certified(prefers_b) == (True, pytest.approx(1.0, abs=1e-12))
    assert certified(prefers_a)[0] is False
    assert certified(prefers_b, [prefers_a]) == (False, pytest.approx(0.0, abs=1e-12))
    assert certified(prefers_b, [reward]) == (True, pytest.approx(0.5, abs=1e-12))
    # the order does not matter, and a reward repeated changes nothing
    assert certified(prefers_a, [prefers_b])[0] is False
    assert certified(reward, [reward, prefers_b]) == (True, pytest.approx(0.5, abs=1e-12))


def last_move_layout():
    """3x3, one expert from (0,0) to (2,0), no obstacle, T = 3, deterministic moves::

        S . G     demonstrations: E E stay, and S NE E (which arrives only at s_T)
        . . .     demonstrated actions: E, stay, S, NE; cells (0,0) (1,0) (2,0) (0,1)
        . . .

    With every other unseen feature forbidden and (2,1) open, the expert at the goal at
    the last decision (t = 2: nothing after it is scored) ties E (off the grid), stay, NE
    (off the grid) and S, which lands on (2,1) at s_T: probability 1/4, counted by the
    evaluation's classification (the true CMG scores s_T), never by the certificate (a last
    move is chance, not preference)."""
    layout = GridLayout(size=3, starts=((0, 0),), goals=((2, 0),))
    model, solver, reward = problem(layout, horizon=3)
    demos = demos_of(model, one_expert("E E stay"), one_expert("S NE E"))
    return model, solver, reward, demos


@pytest.mark.parametrize("feature", ["cell(2,1)", "action W"])
def test_a_feature_only_the_last_move_accrues_is_not_certified(feature):
    """(2,1) is entered only by the last move (S, landing at s_T); W likewise is taken only
    at the last decision (from the goal to the demonstrated (1,0)), tied with E, stay and
    NE: probability 1/4 each for the evaluation, none for the certificate."""
    model, solver, reward, demos = last_move_layout()
    basis = SharedIndicatorCostBasis(model)
    j = basis.names.index(feature)
    evaluation = classify_features(solver=solver, reward=reward, cost_basis=basis,
                                   demonstrations=demos)
    assert float(evaluation.probability[j]) == pytest.approx(0.25, abs=1e-12)
    assert feature in names(evaluation, evaluation.required)
    cert = certify_constraints(solver=solver, reward=reward, cost_basis=basis,
                               demonstrations=demos)
    assert float(cert.probability[j]) == 0.0
    assert feature not in names(cert, cert.required)


# ------------------------------------------------------------------ the grid rows' rule
@pytest.fixture(scope="module")
def rule_runs(tmp_path_factory):
    return {rule: finished_run(tmp_path_factory, rule, f"algo.constraint_rule={rule}")
            for rule in ("certificate", "threshold")}


def learner_rows(run_dir):
    res = json.loads((run_dir / "results.json").read_text())
    return [row for m in ("D-ICRL", "C-ICRL") for row in res["methods"][m]["learners"]]


def test_certificate_rows_list_the_certified_features(rule_runs):
    for row in learner_rows(rule_runs["certificate"]):
        assert row["constraint_rule"] == "certificate"
        assert sorted(row["constraints"]) == sorted(row["certificate_probability"])
        assert all(p >= 1e-3 for p in row["certificate_probability"].values())
        assert row["certificate_candidates"] > 0 and row["n_learned"] == len(row["constraints"])
        assert "pruned" not in row  # pruning belongs to the threshold rule


def test_the_paper_threshold_rule_stays_selectable(rule_runs):
    cert, thresh = (learner_rows(rule_runs[r]) for r in ("certificate", "threshold"))
    for a, b in zip(cert, thresh, strict=True):
        assert b["constraint_rule"] == "threshold" and "certificate_probability" not in b
        # the training is the same: the paper's rule's rates before pruning agree
        assert (a["FPR_before_pruning"], a["FNR_before_pruning"]) == \
            (b["FPR_before_pruning"], b["FNR_before_pruning"])


def test_the_drones_refuse_the_certificate():
    from common import check_config
    from config_checks import ConfigError

    cfg = compose_train("experiment=table2_quick", "algo.constraint_rule=certificate")
    with pytest.raises(ConfigError, match="constraint_rule=threshold"):
        check_config(cfg)


def test_overlapping_features_are_asked_about_their_own_support():
    """thick_wall (test_identifiability) with its cells and two regions over them:
    R = {(1,1), (1,0)} and W = the whole wall. Each tested with the other features of its
    kind forbidden only outside its support: the cells (1,1) and (2,1) are shortcuts
    (probability 1, as alone); R holds (1,1), W both: required. Asked again with the
    narrower required features forbidden inside: R is left with the dead end (1,0), not
    entered, and is dropped; W is left with the top row (1,0) (2,0), a 3-move route to
    the goal that neither cell alone opens, and stays. Without ``open_overlaps`` every
    wall cell is covered by a region while it is tested, and nothing is required."""
    from dicrl_torch.features.bases import RegionIndicatorCostBasis

    model, solver, reward, demos = thick_wall()
    wall = [(1, 0), (2, 0), (1, 1), (2, 1)]
    basis = RegionIndicatorCostBasis(model, regions={"R": [(1, 1), (1, 0)], "W": wall})
    kw = dict(solver=solver, reward=reward, cost_basis=basis, demonstrations=demos)
    cert = certify_constraints(**kw)
    assert names(cert, cert.required) == {"cell(1,1)", "cell(2,1)", "region W"}
    r = basis.names.index("region R")
    assert float(cert.probability[r]) == pytest.approx(0.0, abs=1e-12)
    assert float(cert.probability[basis.names.index("region W")]) == pytest.approx(1.0)
    closed = classify_features(**kw, temperature=0.0, min_probability=1e-3, last_move=False)
    assert not closed.required.any()
    # Indicator bases have no overlaps: the certificate is the same either way.
    cells = SharedIndicatorCostBasis(model)
    kw["cost_basis"] = cells
    opened = classify_features(**kw, temperature=0.0, last_move=False, open_overlaps=True)
    shut = classify_features(**kw, temperature=0.0, last_move=False)
    assert torch.equal(opened.required, shut.required)
    assert torch.equal(opened.probability.nan_to_num(-1), shut.probability.nan_to_num(-1))
