"""The grid's deep cost basis (dicrl_torch.features.grid_local) against a brute-force
loop and its ignorance of the obstacles; the grid's region scores
(dicrl_torch.runs.grid_regions) against dense enumeration on tiny instances."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch

from dicrl_torch.algos.identifiability import check_indicator_basis
from dicrl_torch.envs.grid import ACTIONS, GridLayout, TabularGridModel
from dicrl_torch.features.bases import SharedIndicatorCostBasis
from dicrl_torch.features.grid_local import GridLocalReLUBasis
from dicrl_torch.runs.grid_regions import (
    grid_forbidden,
    grid_undetermined,
    predicted_cost_floor,
)

torch.set_num_threads(1)


def _model(size=4, n_experts=2, obstacles=((1, 1), (2, 1)), forbidden=("NE",),
           collision=True) -> TabularGridModel:
    starts = ((0, 0), (size - 1, 0), (0, size - 1))[:n_experts]
    goals = ((size - 1, size - 1), (0, size - 1), (size - 1, 0))[:n_experts]
    layout = GridLayout(size=size, starts=starts, goals=goals, obstacles=obstacles,
                        forbidden_actions=forbidden, collision_constraint=collision)
    return TabularGridModel(layout=layout, horizon=4, gamma=0.9)


def _unit(net, x: np.ndarray, k: int) -> float:
    """A LocalReLUBasis position unit by hand: the polygonal norm as a sum over its
    directions."""
    nu = sum(abs(float(d @ (x - net.centres[k].numpy()))) for d in net.directions.numpy())
    return max(0.0, 1.0 - nu / float(net.radii[k]))


def _ring(net, sep: float, r: int) -> float:
    return max(0.0, 1.0 - abs(sep - float(net.rings[r])) / float(net.ring_widths[r]))


@pytest.mark.parametrize("n_experts", [2, 3])
def test_the_features_are_the_brute_force_loop(n_experts):
    """φ(s, a) of every joint state-action pair, by hand from the networks' centres,
    radii, directions and rings, equals the factored features' dense form."""
    model = _model(size=3 if n_experts == 3 else 4, n_experts=n_experts)
    basis = GridLocalReLUBasis(model, density=1.0, scales=(1, 2), n_rings=6)
    dense = basis().dense().numpy()  # [S, A, l]
    pos, mov = basis.positions, basis.moves
    xy = [np.array(model.layout.xy(c), float) for c in range(model.n_cells)]
    names = basis.names
    S1, A1 = model.n_cells, model.n_actions
    rng = np.random.default_rng(0)
    joint_states = list(itertools.product(range(S1), repeat=n_experts))
    joint_actions = list(itertools.product(range(A1), repeat=n_experts))
    for s in [joint_states[k] for k in rng.choice(len(joint_states), 20, replace=False)]:
        for a in [joint_actions[k] for k in rng.choice(len(joint_actions), 5, replace=False)]:
            want = np.zeros(len(names))
            for col, name in enumerate(names):
                kind = name.rstrip("0123456789")
                k = int(name[len(kind):])
                if kind == "local":
                    want[col] = sum(_unit(pos, xy[c], k) for c in s)
                elif kind == "move":
                    want[col] = sum(_unit(mov, np.array(ACTIONS[b][1:], float), k) for b in a)
                else:
                    want[col] = sum(
                        _ring(pos, sum(abs(float(d @ (xy[s[i]] - xy[s[j]])))
                                       for d in pos.directions.numpy()), k)
                        for i in range(n_experts) for j in range(i + 1, n_experts))
            flat_s = int(np.ravel_multi_index(s, (S1,) * n_experts))
            flat_a = int(np.ravel_multi_index(a, (A1,) * n_experts))
            np.testing.assert_allclose(dense[flat_s, flat_a], want, atol=1e-12)
    # Every kept unit is positive somewhere; every dropped one nowhere on the lattice.
    assert (dense > 0).any((0, 1)).all()


def test_the_weights_know_nothing_of_the_obstacles():
    """Moving the obstacles, changing the forbidden moves and the collision rule leaves
    every weight, name and feature as they were."""
    a = GridLocalReLUBasis(_model())
    b = GridLocalReLUBasis(_model(obstacles=((2, 2),), forbidden=("S", "W"), collision=False))
    sa, sb = a.state_dict(), b.state_dict()
    assert sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)
    assert a.names == b.names
    assert torch.equal(a().local, b().local) and torch.equal(a().joint, b().joint)


def test_supports_are_regions_and_the_certificate_takes_the_basis():
    """Exact zeros: every feature vanishes somewhere (so it can be a constraint), the
    finest units hold single cells, the ring at 0 holds the collisions alone; the
    identifiability checks accept the basis."""
    model = _model(size=9)
    basis = GridLocalReLUBasis(model)
    f = basis()
    assert f.local.min() >= 0 and f.joint.min() >= 0
    check_indicator_basis(basis, model)
    sizes = [len(c) for c in basis.region_cells.values()]
    assert min(sizes) == 1 and sizes.count(1) > model.n_cells // 2
    ring0 = f.joint[:, 0].reshape(model.n_cells, model.n_cells)
    assert torch.equal(ring0 > 0, torch.eye(model.n_cells, dtype=torch.bool))
    assert basis.names[-len(f.joint_columns)] == "ring0"


def test_settings_are_checked():
    for kwargs, match in [({"density": 0}, "density"), ({"move_centres": 0}, "move_centres"),
                          ({"n_rings": -1}, "n_rings"), ({"overlap": 0.5}, "overlap"),
                          ({"scales": (1, 1)}, "scales")]:
        with pytest.raises(ValueError, match=match):
            GridLocalReLUBasis(_model(), **kwargs)


# ------------------------------------------------------------------ region scores
@pytest.mark.parametrize("n_experts", [2, 3])
def test_the_cost_floor_is_the_dense_minimum_over_joint_actions(n_experts):
    model = _model(size=3, n_experts=n_experts)
    for basis in (SharedIndicatorCostBasis(model), GridLocalReLUBasis(model, density=1.0)):
        f = basis()
        learned = np.random.default_rng(1).random(basis.dim) < 0.3
        dense = (f.dense() @ torch.as_tensor(learned, dtype=torch.float64)).amin(1)
        floor = predicted_cost_floor(f, learned, model.n_cells)
        assert floor.shape == (model.n_cells,) * n_experts
        torch.testing.assert_close(floor.reshape(-1), dense, rtol=0, atol=1e-12)


def test_the_truth_is_obstacles_and_collisions():
    model = _model(size=3, n_experts=2, obstacles=((1, 1),))
    truth = grid_forbidden(model)
    for s1, s2 in itertools.product(range(9), repeat=2):
        assert bool(truth[s1, s2]) == (s1 == 4 or s2 == 4 or s1 == s2)
    free = _model(size=3, n_experts=2, obstacles=((1, 1),), collision=False)
    assert not grid_forbidden(free)[0, 0]


def test_undetermined_states_come_from_the_demonstrations():
    """On a 5x5 grid demonstrations that walk the top row at separation >= 2: a cell two
    rows down is farther than one move from every demonstrated cell; experts closer
    than 2 are undetermined too; forbidden states are never undetermined."""
    model = _model(size=5, n_experts=2, obstacles=((3, 4),))
    layout = model.layout
    states = np.array([[[layout.cell((0, 0)), layout.cell((2, 0))],
                        [layout.cell((1, 0)), layout.cell((3, 0))],
                        [layout.cell((2, 0)), layout.cell((4, 0))]]])  # [1, 3, 2]
    free = ~grid_forbidden(model)
    und, band = grid_undetermined(layout, free, states)
    assert (band["step"], band["min_separation"]) == (1, 2)
    assert band["near"].tolist() == [y <= 1 for y in range(5) for _ in range(5)]
    c = layout.cell
    assert not und[c((0, 1)), c((4, 1))]  # both within a move of the top row, apart
    assert und[c((0, 2)), c((4, 0))]  # expert 1 two rows down
    assert und[c((0, 1)), c((1, 1))]  # adjacent: closer than the demonstrations
    assert not und[c((3, 4)), c((0, 4))] and not und[c((0, 0)), c((0, 0))]  # forbidden


def test_cell_scores_of_the_true_set_are_exact(tmp_path):
    """A GridTask scoring the shared cell basis' true set recovers every forbidden joint
    state and nothing else (recall, precision and IoU 1, obstacle recall 1 at FPR 0,
    moves exact); the empty set recovers nothing; the deep basis learning the units
    inside the obstacles scores by hand."""
    task = _task(SharedIndicatorCostBasis)
    true = task.cost_basis.true_constraints().numpy()
    r = task.region_rates(true)
    assert (r["region_recall"], r["region_precision"], r["region_iou"]) == (1.0, 1.0, 1.0)
    assert task.required_rates(true) == {"obstacle_recall_required": 1.0}
    assert task.required_rates(np.zeros_like(true), task.demos) == {
        "obstacle_recall_required": 0.0, "obstacle_recall_required_bound": 1.0}
    assert (r["obstacle_recall"], r["obstacle_FPR"], r["move_recall"], r["move_FPR"]) == \
        (1.0, 0.0, 1.0, 0.0)
    empty = task.region_rates(np.zeros_like(true))
    assert empty["region_recall"] == 0.0 and empty["region_precision"] == 1.0
    assert empty["obstacle_recall"] == 0.0 and empty["obstacle_FPR"] == 0.0
    # Every feature the pooled demonstrations leave unused can be learned: the bound is
    # the scores of learning them all, and the true constraints' recall is within it.
    usable = task.usable_features(task.demos).numpy()
    bound = task.recall_bound(task.demos)
    assert bound == task.region_rates(usable)["region_recall"]
    assert bound >= task.region_rates(true & usable)["region_recall"]

    deep = _task(GridLocalReLUBasis, density=1.0)
    feats = deep.cost_basis()
    inside = np.array([set(deep.cost_basis.region_cells.get(n, ())) <= {5, 6}
                       and n in deep.cost_basis.region_cells for n in deep.cost_basis.names])
    assert inside.any()
    covered = set().union(*(deep.cost_basis.region_cells[n]
                            for n, on in zip(deep.cost_basis.names, inside, strict=True) if on))
    r = deep.region_rates(inside)
    assert r["obstacle_recall"] == len(covered) / 2 and r["obstacle_FPR"] == 0.0
    assert r["move_recall"] == 0.0 and r["region_precision"] == 1.0
    assert sorted(deep.predicted_cells(inside)) == sorted(covered)
    assert feats.local.shape[-1] == deep.cost_basis.dim
    # the required obstacles: read from the cell basis' own classification, or asked anew
    # with a shared cell basis beside another basis: the same demonstrations, one answer
    assert torch.equal(task.required_obstacles(), deep.required_obstacles())


def _task(cost, **kwargs):
    """A GridTask on a 4x4 grid, 2 experts, obstacles (1,1) and (2,1), NE forbidden."""
    from dicrl_torch.features.bases import GoalClosenessRewardBasis
    from dicrl_torch.runs.grid import GridTask
    from dicrl_torch.solvers.factored import FactoredSoftBellman

    model = _model()
    rb = GoalClosenessRewardBasis(model)
    return GridTask(layout=model.layout, model=model,
                    solver=FactoredSoftBellman(model=model, dtype=torch.float64),
                    reward_basis=rb, cost_basis=cost(model, **kwargs),
                    true_reward_weights=rb.true_weights(), split=[3, 3], seed=0,
                    eval_episodes=2, constraint_rule="threshold")


def test_a_basis_that_can_express_nothing_is_refused_naming_the_fix():
    """A frozen sigmoid network is positive everywhere: every feature is accrued by every
    demonstration, no learner can learn any, and the run is refused before training; the
    deep basis and the cells pass."""
    from dicrl_torch.features.bases import FrozenModuleBasis, random_mlp

    sigmoid = _task(lambda model: FrozenModuleBasis(model, random_mlp(out_dim=4), out_dim=4))
    with pytest.raises(ValueError, match="local_relu_grid"):
        sigmoid.check_expressive()
    for cost in (SharedIndicatorCostBasis, GridLocalReLUBasis):
        _task(cost).check_expressive()
