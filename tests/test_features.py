"""Feature bases: shapes, semantics, ground truth, validation, the generic
frozen-module basis, and the one protocol every shipped basis satisfies."""

from __future__ import annotations

import inspect
from pathlib import Path

import pytest
import torch
from hydra.utils import get_class, instantiate
from omegaconf import OmegaConf
from torch import nn

from dicrl_torch.envs.drones import NOMINAL_STARTS
from dicrl_torch.envs.grid import ACTION_NAMES, SCOBEE_REGIONS, GridLayout, TabularGridModel
from dicrl_torch.features.base import Basis, ConstraintBasis
from dicrl_torch.features.bases import (
    FactoredFeatures,
    FrozenModuleBasis,
    GoalClosenessRewardBasis,
    LinearHead,
    PerExpertIndicatorCostBasis,
    RegionIndicatorCostBasis,
    SharedIndicatorCostBasis,
    random_mlp,
)


@pytest.fixture(params=[1, 2, 3])
def model(request):
    return TabularGridModel(layout=GridLayout.scobee(request.param), horizon=5)


def test_no_trainable_parameters(model):
    for basis in (GoalClosenessRewardBasis(model), SharedIndicatorCostBasis(model),
                  PerExpertIndicatorCostBasis(model),
                  FrozenModuleBasis(model, random_mlp(out_dim=4), out_dim=4)):
        basis()
        assert not any(p.requires_grad for p in basis.parameters())


def test_cost_basis_dimensions_and_ground_truth(model):
    N = model.n_experts
    shared, per = SharedIndicatorCostBasis(model), PerExpertIndicatorCostBasis(model)
    assert shared.dim == 81 + 9 + 1
    assert per.dim == N * 90 + 1
    # 11 obstacles + NE, NW + collision (only with two or more experts).
    assert int(shared.true_constraints().sum()) == 11 + 2 + (N > 1)
    assert int(per.true_constraints().sum()) == N * 13 + (N > 1)
    names = [n for n, c in zip(shared.names, shared.true_constraints(), strict=True) if c]
    assert "cell(4,5)" in names and "action NE" in names and "action NW" in names
    assert torch.equal(shared.true_weights(), shared.true_constraints().double())


def test_indicator_semantics_on_joint_pairs():
    model = TabularGridModel(layout=GridLayout.scobee(2), horizon=5)
    f = SharedIndicatorCostBasis(model)()
    cells = torch.tensor([[40, 40], [0, 80]])  # collision at (4,4); apart
    acts = torch.tensor([[ACTION_NAMES.index("NE"), 0], [1, 1]])
    phi = f.at(cells, acts, model.n_cells)
    assert phi[0, 40] == 2.0  # both experts stand in cell 40
    assert phi[0, 81 + ACTION_NAMES.index("NE")] == 1.0 and phi[0, 81] == 1.0
    assert phi[0, -1] == 1.0 and phi[1, -1] == 0.0  # collision indicator
    assert phi[1, 81 + 1] == 2.0  # both take N
    per = PerExpertIndicatorCostBasis(model)()
    phi_p = per.at(cells, acts, model.n_cells)
    assert phi_p[0, 40] == 1.0 and phi_p[0, 90 + 40] == 1.0


def test_region_basis_adds_one_column_per_region_to_the_shared_basis(model):
    shared_basis, regions = SharedIndicatorCostBasis(model), RegionIndicatorCostBasis(model)
    shared, f = shared_basis(), regions()
    assert regions.names == shared_basis.names[:90] + ["region blue", "region green",
                                                       "collision"]
    # Cells, actions and collision are the shared basis' columns.
    assert torch.equal(f.local[..., :90], shared.local[..., :90])
    assert torch.equal(f.joint, shared.joint) and f.joint_columns.tolist() == [92]
    # A region's column is the sum of its cells' columns: 1 for each expert standing in it.
    for r, (_, cells) in enumerate(SCOBEE_REGIONS):
        idx = [model.layout.cell(c) for c in cells]
        want = shared.local[..., idx].sum(-1)
        assert torch.equal(f.local[..., 90 + r], want)
    two = TabularGridModel(layout=GridLayout.scobee(2), horizon=5)
    phi = RegionIndicatorCostBasis(two)().at(torch.tensor([[4, 13]]),
                                             torch.tensor([[0, 0]]), two.n_cells)
    assert phi[0, 90] == 2.0 and phi[0, 91] == 0.0  # both experts on the blue wall


def test_region_basis_ground_truth_follows_scobee():
    model = TabularGridModel(layout=GridLayout.scobee(2), horizon=5)
    basis = RegionIndicatorCostBasis(model)
    true = [n for n, c in zip(basis.names, basis.true_constraints(), strict=True) if c]
    # The walls are constrained through their colours, the chevron cell by cell.
    assert true == ["cell(2,3)", "cell(6,3)", "cell(3,4)", "cell(5,4)", "cell(4,5)",
                    "action NE", "action NW", "region blue", "region green", "collision"]
    # A region that holds a free cell is no constraint, and its obstacles keep theirs.
    mixed = RegionIndicatorCostBasis(model, regions={"top": [(4, 2), (4, 3)]})
    names = [n for n, c in zip(mixed.names, mixed.true_constraints(), strict=True) if c]
    assert "region top" not in names and "cell(4,2)" in names
    assert mixed.region_cells == {"region top": (22, 31)}


@pytest.mark.parametrize("regions, match", [
    (5, "must map names to lists of"),
    ([(4, 0)], "region names must be distinct non-empty strings"),
    ({"a": []}, "region 'a' has no cells"),
    ({"a": [(4, 9)]}, r"cells \[\(4, 9\)\] lie outside the 9x9 grid"),
    ({"a": [4, 0]}, r"must be \(x, y\) pairs"),
])
def test_region_basis_refuses_bad_regions(regions, match):
    model = TabularGridModel(layout=GridLayout.scobee(1), horizon=3)
    with pytest.raises(ValueError, match=match):
        RegionIndicatorCostBasis(model, regions=regions)
    with pytest.raises(ValueError, match=match):
        GridLayout(size=9, starts=((0, 0),), goals=((8, 8),), regions=regions)


def test_region_basis_without_regions_is_the_shared_basis():
    model = TabularGridModel(layout=GridLayout.open_grid(5, 2), horizon=3)
    basis, shared = RegionIndicatorCostBasis(model), SharedIndicatorCostBasis(model)
    assert basis.names == shared.names and basis.region_cells == {}
    assert torch.equal(basis().local, shared().local)
    assert torch.equal(basis.true_constraints(), shared.true_constraints())
    with pytest.raises(ValueError, match="distinct"):
        GridLayout(size=5, starts=((0, 0),), goals=((4, 4),),
                   regions=(("a", ((1, 1),)), ("a", ((2, 2),))))


def test_goal_closeness_reward(model):
    rb = GoalClosenessRewardBasis(model)
    f = rb()
    layout = model.layout
    for i, goal in enumerate(layout.goal_cells):
        assert f.local[i, goal, 0, 2 * i] == 1.0 and f.local[i, goal, 0, 2 * i + 1] == 1.0
        start = layout.start_cells[i]
        assert f.local[i, start, 3, 2 * i] == pytest.approx(0.0)  # 8 cells away
        assert f.local[i, :, :, : 2 * i].abs().sum() == 0  # only its own block
    r = f.weighted(rb.true_weights())
    goal = layout.goal_cells[0]
    assert r.local[0, goal].max() == pytest.approx(3.0)  # largest at the goal
    assert r.local[0].max() == r.local[0, goal].max()


def test_linear_head_and_dense_agree():
    model = TabularGridModel(layout=GridLayout.open_grid(3, 2), horizon=3)
    f = SharedIndicatorCostBasis(model)()
    w = torch.rand(f.dim, dtype=torch.float64)
    head = LinearHead(f.dim, init=w)
    assert torch.allclose(head(f).dense(), torch.einsum("sal,l->sa", f.dense(), w))
    with pytest.raises(ValueError, match="shape"):
        LinearHead(3, init=torch.zeros(4))


def test_frozen_module_basis_swaps_in(model):
    basis = FrozenModuleBasis(model, random_mlp(out_dim=5, seed=3), out_dim=5, per_expert=True)
    f = basis()
    assert f.local.shape == (model.n_experts, 81, 9, 5 * model.n_experts)
    assert 0.0 <= float(f.local.min()) and float(f.local.max()) <= 1.0
    assert torch.equal(FrozenModuleBasis(model, random_mlp(out_dim=5, seed=3), out_dim=5,
                                         per_expert=True)().local, f.local)


def test_basis_range_and_width_are_checked():
    model = TabularGridModel(layout=GridLayout.scobee(1), horizon=3)
    unbounded = nn.Sequential(nn.Linear(11, 3))  # outputs leave [0, 1]
    with torch.no_grad():
        unbounded[0].bias.fill_(5.0)
    with pytest.raises(ValueError, match="leave"):
        FrozenModuleBasis(model, unbounded, out_dim=3)()
    with pytest.raises(ValueError, match="out_dim"):
        FrozenModuleBasis(model, random_mlp(out_dim=4), out_dim=6)()
    with pytest.raises(ValueError, match="shape"):
        SharedIndicatorCostBasis(model)().weighted(torch.zeros(3))


SHIPPED = sorted((Path(__file__).resolve().parents[1] / "configs" / "features").rglob("*.yaml"))


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: f"{p.parent.name}/{p.stem}")
def test_every_shipped_basis_is_a_basis(path):
    """Every basis of configs/features/**, built as the runner builds it (a grid basis on
    the tabular model), satisfies features.base.Basis, with the shapes it documents."""
    cfg = OmegaConf.load(path)
    build = instantiate(cfg, _partial_=True)
    if "model" in inspect.signature(get_class(cfg._target_)).parameters:
        model = TabularGridModel(layout=GridLayout.scobee(2), horizon=3)
        basis = build(model=model)
    else:
        basis = build()
    assert isinstance(basis, Basis)
    assert basis.dim == len(basis.names) >= 1 and basis.max_value > 0
    if basis.env_kind == "grid":
        f = basis()
        assert isinstance(f, FactoredFeatures)
        assert f.local.shape == (2, model.n_cells, model.n_actions, basis.dim)
    else:
        assert basis.env_kind == "continuous"
        states = torch.zeros(3, 2, 4, dtype=torch.float64)
        states[..., :2] = torch.tensor(NOMINAL_STARTS, dtype=torch.float64)
        assert basis(states).shape == (3, basis.dim)
    # A cost basis knows the true constraints, but for a neural one (no feature is true:
    # the game's region truth scores it, dicrl_torch.region).
    if path.parent.name == "cost" and not cfg._target_.endswith(("ModuleBasis",
                                                                  "LocalReLUBasis")):
        assert isinstance(basis, ConstraintBasis)
        truth = basis.true_constraints()
        assert truth.dtype == torch.bool and truth.shape == (basis.dim,)


def test_a_module_without_the_protocol_is_not_a_basis():
    assert not isinstance(nn.Linear(2, 2), Basis)
    assert not isinstance(FrozenModuleBasis(TabularGridModel(layout=GridLayout.scobee(1),
                                                             horizon=3),
                                            random_mlp(out_dim=2), out_dim=2), ConstraintBasis)
