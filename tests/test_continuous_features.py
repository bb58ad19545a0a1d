"""Feature bases of continuous multi-agent environments (issue 27), against independent
truth: brute-force loops, hand-picked points, dense sampling and the Gaussian kernel
random Fourier features approximate."""

from __future__ import annotations

import itertools
import math
import re

import numpy as np
import pytest
import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf
from torch import nn

from dicrl_torch.demos.continuous import ContinuousDemonstrations
from dicrl_torch.features.base import Basis, ConstraintBasis
from dicrl_torch.features.continuous import (
    ModuleBasis,
    PositionCellBasis,
    RandomFourierBasis,
    ScaledSigmoid,
    bounded_mlp,
    load_module_weights,
)

torch.set_num_threads(1)
ARENA = {"bounds": ((-1.5, 1.5), (-1.5, 1.5)), "proximity_radius": 0.4}


def states(shape, n=3, d=4, seed=0, lo=-1.3, hi=1.3):
    return np.random.default_rng(seed).uniform(lo, hi, (*shape, n, d))


# ============================================================ PositionCellBasis
def brute_cells(s, bounds, nx, ny, cols=(0, 1)):
    """Loops over samples, agents and cells; outside the arena = nearest border cell."""
    (x0, x1), (y0, y1) = bounds
    w, h = (x1 - x0) / nx, (y1 - y0) / ny
    flat = s.reshape(-1, *s.shape[-2:])
    out = np.zeros((len(flat), nx * ny))
    for b, joint in enumerate(flat):
        for agent in joint:
            x, y = agent[cols[0]], agent[cols[1]]
            hits = []
            for iy, ix in itertools.product(range(ny), range(nx)):
                lo_x, hi_x = x0 + ix * w, x0 + (ix + 1) * w
                lo_y, hi_y = y0 + iy * h, y0 + (iy + 1) * h
                in_x = (lo_x <= x < hi_x) or (ix == 0 and x < lo_x) or (ix == nx - 1 and x >= hi_x)
                in_y = (lo_y <= y < hi_y) or (iy == 0 and y < lo_y) or (iy == ny - 1 and y >= hi_y)
                if in_x and in_y:
                    hits.append(iy * nx + ix)
            assert len(hits) == 1
            out[b, hits[0]] += 1
    return out.reshape(*s.shape[:-2], nx * ny)


def brute_proximity(s, radius, cols=(0, 1)):
    flat = s.reshape(-1, *s.shape[-2:])
    out = [float(any(math.dist(p[list(cols)], q[list(cols)]) < radius
                     for p, q in itertools.combinations(joint, 2))) for joint in flat]
    return np.array(out).reshape(*s.shape[:-2], 1)


@pytest.mark.parametrize("n_agents,nx,ny,cols", [(3, 4, 4, (0, 1)), (2, 3, 5, (2, 0)),
                                                 (1, 2, 1, (1, 3)), (4, 6, 2, (0, 1))])
def test_cells_and_proximity_match_brute_force(n_agents, nx, ny, cols):
    bounds = ((-1.0, 1.0), (-0.5, 1.5))
    basis = PositionCellBasis(n_agents=n_agents, bounds=bounds, n_per_axis=(nx, ny),
                              proximity_radius=0.6, position_columns=cols)
    s = states((5, 3), n=n_agents)
    phi = basis(s).numpy()
    assert phi.shape == (5, 3, nx * ny + 1) and basis.dim == nx * ny + 1
    assert np.array_equal(phi[..., :-1], brute_cells(s, bounds, nx, ny, cols))
    assert np.array_equal(phi[..., -1:], brute_proximity(s, 0.6, cols))
    assert (phi[..., :-1].sum(-1) == n_agents).all()  # every agent counted once
    assert basis.max_value == n_agents and phi.max() <= n_agents


def test_cells_on_hand_picked_points():
    basis = PositionCellBasis(n_agents=3, bounds=((0, 3), (0, 2)), n_per_axis=(3, 2),
                              proximity_radius=0.5)
    assert basis.names == ["cell(0,0)", "cell(1,0)", "cell(2,0)", "cell(0,1)", "cell(1,1)",
                           "cell(2,1)", "proximity"]
    s = torch.tensor([[[1.0, 0.0, 9, 9], [2.99, 1.99, 0, 0], [1.2, 0.4, 0, 0]],
                      [[3.0, 2.0, 0, 0], [-5.0, 0.7, 0, 0], [0.5, 1.5, 0, 0]]],
                     dtype=torch.float64)
    phi = basis(s)
    # Sample 0: (1, 0) on the left edge of cell (1,0); (2.99, 1.99) in (2,1); (1.2, 0.4)
    # in (1,0), 0.45 from the first agent: proximity.
    assert phi[0].tolist() == [0, 2, 0, 0, 0, 1, 1]
    # Sample 1: the top-right corner and a point far left count in the border cells.
    assert phi[1].tolist() == [1, 0, 0, 1, 0, 1, 0]
    with pytest.raises(ValueError, match=r"states must have shape \[\.\.\., 3, d\]"):
        PositionCellBasis(n_agents=3, bounds=((0, 3), (0, 2)),
                          proximity_radius=0.5)(s[:, :2])


def brute_overlap(rect, centre, radius, k=201):
    """Dense interior sampling: does any point of the cell lie strictly inside the disc?"""
    x0, y0, x1, y1 = rect
    xs, ys = np.meshgrid(np.linspace(x0, x1, k), np.linspace(y0, y1, k))
    return bool((np.hypot(xs - centre[0], ys - centre[1]) < radius).any())


def test_true_constraints_disc_overlap_and_proximity():
    basis = PositionCellBasis(n_agents=2, bounds=((0, 4), (0, 4)), n_per_axis=4,
                              proximity_radius=0.3)
    truth = basis.true_constraints((2.0, 2.0), 0.5, min_distance=0.3)
    assert truth.dtype == torch.bool and truth.shape == (17,) and bool(truth[-1])
    named = {basis.names[j] for j in np.flatnonzero(truth[:-1].numpy())}
    assert named == {"cell(1,1)", "cell(2,1)", "cell(1,2)", "cell(2,2)"}
    # Radius 1: the edge neighbours only touch the rim (free); a little more and they
    # overlap; the diagonal cells are sqrt(2) away.
    assert basis.true_constraints((2.0, 2.0), 1.0)[:-1].sum() == 4
    assert basis.true_constraints((2.0, 2.0), 1.01)[:-1].sum() == 12
    assert not basis.true_constraints((2.0, 2.0), 1.0)[-1]  # no min_distance: free
    rects = basis.cell_rectangles()
    for centre, radius in (((0.3, 3.7), 0.8), ((2.5, 1.0), 1.3), ((5.0, 5.0), 1.5)):
        got = basis.true_constraints(centre, radius)[:-1].numpy()
        want = [brute_overlap(r, centre, radius) for r in rects]
        assert got.tolist() == want
    both = basis.true_constraints([[0.3, 3.7], [2.5, 1.0]], [0.8, 1.3])[:-1].numpy()
    assert both.tolist() == [brute_overlap(r, (0.3, 3.7), 0.8) or brute_overlap(r, (2.5, 1.0), 1.3)
                             for r in rects]


def test_ground_truth_from_constructor_and_refusals():
    basis = PositionCellBasis(n_agents=3, bounds=((0, 4), (0, 4)), n_per_axis=4,
                              proximity_radius=0.3, obstacle_centre=(2.0, 2.0),
                              obstacle_radius=0.5, min_distance=0.3)
    assert isinstance(basis, ConstraintBasis) and isinstance(basis, Basis)
    assert basis.env_kind == "continuous"
    assert basis.true_constraints().sum() == 5
    assert torch.equal(basis.true_weights(), basis.true_constraints().double())
    with pytest.raises(ValueError, match="no ground truth"):
        PositionCellBasis(n_agents=2, **ARENA).true_constraints()
    with pytest.raises(ValueError, match=r"proximity_radius=0.5"):
        basis.true_constraints(min_distance=0.5)
    with pytest.raises(ValueError, match="disc_radius"):
        basis.true_constraints([[0, 0], [1, 1]], [0.1, 0.2, 0.3])
    with pytest.raises(ValueError, match="disc_centre"):
        basis.true_constraints((1, 2, 3), 0.1)
    for kw, msg in (({"bounds": ((1, 0), (0, 1))}, "bounds"), ({"n_per_axis": 0}, "n_per_axis"),
                    ({"position_columns": (1, 1)}, "position_columns"),
                    ({"position_columns": (0, 4), "state_dim": 4}, "state_dim=4"),
                    ({"proximity_radius": -1}, "proximity_radius")):
        with pytest.raises(ValueError, match=msg):
            PositionCellBasis(n_agents=2, **{**ARENA, **kw})
    sliced = PositionCellBasis(n_agents=2, position_columns=slice(2, 4), **ARENA)
    assert sliced.position_columns == (2, 3)
    with pytest.raises(ValueError, match=r"position_columns \(2, 3\) do not fit"):
        sliced(np.zeros((2, 2)))


# ======================================================================= ModuleBasis
class Const(nn.Module):
    """Returns a fixed row per sample (plus an unused parameter, so it has a dtype)."""

    def __init__(self, row):
        super().__init__()
        self.row = torch.tensor(row, dtype=torch.float32)
        self.p = nn.Parameter(torch.zeros(1))

    def forward(self, x):
        return self.row.expand(x.shape[0], -1) + 0 * self.p


@pytest.mark.parametrize("row,dim,message", [
    ([0.2, -0.5, 0.1], 3, r"features leave \[0, 1.0\]: 2 of 6 values are outside \(first "
                          r"-0.5 at index \(0, 1\), feature 'f1'.*ScaledSigmoid"),
    ([0.2, 1.5, 0.1], 3, r"first 1.5 at index \(0, 1\).*ScaledSigmoid"),
    ([0.2, float("nan"), 0.1], 3, r"first nan at index \(0, 1\).*2 NaN/inf.*ScaledSigmoid"),
    ([0.2, 0.5, 0.1, 0.3], 3, r"returns 4 features per sample but dim = 3; set dim=4"),
])
def test_module_outputs_are_refused_naming_basis_values_and_fix(row, dim, message):
    basis = ModuleBasis(module=Const(row), dim=dim)
    with pytest.raises(ValueError, match=re.escape("ModuleBasis(Const)") + ".*" + message):
        basis(states((2,), n=2, d=3))


def test_module_basis_shapes_dtypes_and_freezing():
    net = bounded_mlp(3 * 4, 5, hidden=(16, 8), max_value=2.0, seed=1)
    basis = ModuleBasis(module=net, dim=5, max_value=2.0, n_agents=3, state_dim=4)
    assert isinstance(basis, Basis) and basis.names == ["f0", "f1", "f2", "f3", "f4"]
    assert not any(p.requires_grad for p in basis.parameters())
    s = states((4, 6))
    phi = basis(s)
    assert phi.shape == (4, 6, 5) and phi.dtype == torch.float64
    assert 0 <= float(phi.min()) and float(phi.max()) <= 2.0
    # Per sample: the module sees the joint state flattened agent-major.
    one = net(torch.tensor(s[2, 3].reshape(1, -1), dtype=torch.float32))[0]
    assert torch.allclose(phi[2, 3].float(), one)
    assert basis(torch.tensor(s, dtype=torch.float32)).dtype == torch.float32
    assert basis(s[0, 0]).shape == (5,) and basis(np.zeros((0, 3, 4))).shape == (0, 5)
    # Actions are checked, not used.
    assert torch.equal(basis(s, np.zeros((4, 6, 3, 2))), phi)
    with pytest.raises(ValueError, match="actions of shape"):
        basis(s, np.zeros((4, 5, 3, 2)))
    with pytest.raises(ValueError, match=r"must have shape \[\.\.\., 3, 4\]"):
        basis(s[..., :3])
    bad = s.copy()
    bad[0, 0, 1, 2] = np.nan
    with pytest.raises(ValueError, match=r"NaN or inf.*first at index \(0, 0, 1, 2\)"):
        basis(bad)
    with pytest.raises(ValueError, match="float array"):
        basis(s.astype(np.int64))
    # A frozen feature map: train mode on the basis keeps dropout off.
    drop = ModuleBasis(module=nn.Sequential(nn.Dropout(0.5), bounded_mlp(12, 2, seed=0)), dim=2)
    drop.train()
    assert torch.equal(drop(s), drop(s)) and not drop.net.training


def test_float32_round_off_at_max_value_is_accepted():
    # sigmoid saturates at exactly 1 in float32; 0.3 * 1 in float32 exceeds 0.3 (float64).
    net = nn.Sequential(nn.Linear(4, 2), ScaledSigmoid(0.3))
    with torch.no_grad():
        net[0].bias.fill_(100.0)
    phi = ModuleBasis(module=net, dim=2, max_value=0.3)(states((3,), n=2, d=2))
    assert float(phi.max()) > 0.3 and float(phi.max()) < 0.3 + 1e-7


def test_bounded_mlp_is_seeded_without_touching_the_global_generator():
    before = torch.random.get_rng_state()
    a, b, c = bounded_mlp(6, 3, seed=4), bounded_mlp(6, 3, seed=4), bounded_mlp(6, 3, seed=5)
    assert torch.equal(torch.random.get_rng_state(), before)
    assert all(torch.equal(p, q) for p, q in zip(a.parameters(), b.parameters(), strict=True))
    assert not torch.equal(a[0].weight, c[0].weight)


def test_weights_round_trip_with_weights_only(tmp_path, monkeypatch):
    calls = []
    real_load = torch.load

    def spy(*args, **kwargs):
        calls.append(kwargs.get("weights_only"))
        return real_load(*args, **kwargs)

    monkeypatch.setattr(torch, "load", spy)
    trained = ModuleBasis(module=bounded_mlp(8, 4, seed=11), dim=4)
    path = trained.save_weights(tmp_path / "w" / "feat.pt")
    s = states((7,), n=2, d=4)
    back = ModuleBasis.from_file(path, lambda: bounded_mlp(8, 4, seed=0), dim=4)
    assert torch.equal(back(s), trained(s)) and not torch.equal(
        ModuleBasis(module=bounded_mlp(8, 4, seed=0), dim=4)(s), trained(s))
    # A plain torch.save(state_dict) file, into a built module, through the constructor.
    torch.save(bounded_mlp(8, 4, seed=11).state_dict(), tmp_path / "plain.pt")
    same = ModuleBasis(module=bounded_mlp(8, 4, seed=3), dim=4, weights=tmp_path / "plain.pt")
    assert torch.equal(same(s), trained(s))
    assert calls and all(c is True for c in calls)


def test_weight_files_that_are_not_state_dicts_are_refused(tmp_path):
    torch.save(bounded_mlp(8, 4), tmp_path / "module.pt")  # a pickled module
    with pytest.raises(ValueError, match=r"module.pt' cannot be read with weights_only=True"
                                         r".*state_dict"):
        ModuleBasis.from_file(tmp_path / "module.pt", lambda: bounded_mlp(8, 4), dim=4)
    torch.save(bounded_mlp(8, 5).state_dict(), tmp_path / "wide.pt")
    with pytest.raises(ValueError, match=r"wide.pt' does not fit the module Sequential"):
        load_module_weights(bounded_mlp(8, 4), tmp_path / "wide.pt")
    torch.save([torch.zeros(2)], tmp_path / "list.pt")
    with pytest.raises(ValueError, match="holds a list, not a state_dict"):
        load_module_weights(bounded_mlp(8, 4), tmp_path / "list.pt")
    (tmp_path / "junk.pt").write_bytes(b"garbage")
    with pytest.raises(ValueError, match="junk.pt' cannot be read"):
        load_module_weights(bounded_mlp(8, 4), tmp_path / "junk.pt")
    with pytest.raises(FileNotFoundError, match="missing.pt"):
        load_module_weights(bounded_mlp(8, 4), tmp_path / "missing.pt")
    with pytest.raises(TypeError, match="must be an nn.Module"):
        ModuleBasis(module=lambda x: x, dim=2)


def test_module_basis_from_hydra_config(tmp_path):
    ModuleBasis(module=bounded_mlp(8, 3, seed=2), dim=3).save_weights(tmp_path / "w.pt")
    cfg = OmegaConf.create({
        "_target_": "dicrl_torch.features.continuous.ModuleBasis",
        "module": {"_target_": "dicrl_torch.features.continuous.bounded_mlp",
                   "in_features": 8, "out_features": 3, "hidden": [64], "seed": 0},
        "dim": 3, "n_agents": 2, "state_dim": 4, "weights": str(tmp_path / "w.pt")})
    basis = instantiate(cfg)
    s = states((2,), n=2, d=4)
    assert torch.equal(basis(s), ModuleBasis(module=bounded_mlp(8, 3, seed=2), dim=3)(s))
    cells = instantiate(OmegaConf.create({
        "_target_": "dicrl_torch.features.continuous.PositionCellBasis", "n_agents": 3,
        "bounds": [[-1, 1], [-1, 1]], "n_per_axis": [2, 3], "position_columns": [0, 1],
        "proximity_radius": 0.1, "obstacle_centre": [0, 0], "obstacle_radius": 0.2,
        "min_distance": 0.1}))
    assert cells.dim == 7 and cells.true_constraints().tolist() == [
        False, False, True, True, False, False, True]


# ================================================================ RandomFourierBasis
def test_rff_is_deterministic_per_seed_in_range_and_batched():
    kw = {"n_agents": 3, "state_dim": 4, "n_features": 32, "bandwidth": 0.7}
    a, b = RandomFourierBasis(seed=3, **kw), RandomFourierBasis(seed=3, **kw)
    c = RandomFourierBasis(seed=4, **kw)
    s = states((5, 2))
    assert torch.equal(a(s), b(s)) and not torch.allclose(a(s), c(s))
    assert a(s).shape == (5, 2, 32) and a.names[0] == "rff0" and a.dim == 32
    scaled = RandomFourierBasis(seed=3, max_value=2.5, **kw)(s)
    assert torch.allclose(scaled, 2.5 * a(s))
    assert 0 <= float(scaled.min()) and float(scaled.max()) <= 2.5
    flat = a(s.reshape(10, 3, 4))
    assert torch.equal(flat.reshape(5, 2, 32), a(s))
    with pytest.raises(ValueError, match=r"\[\.\.\., 3, 4\]"):
        a(states((2,), n=2))
    with pytest.raises(ValueError, match="bandwidth must be one number or 4"):
        RandomFourierBasis(n_agents=3, state_dim=4, bandwidth=[1.0, 2.0])
    with pytest.raises(ValueError, match="bandwidth"):
        RandomFourierBasis(n_agents=3, state_dim=4, bandwidth=0.0)


@pytest.mark.parametrize("bandwidth", [0.8, [0.5, 0.5, 2.0, 2.0]])
def test_rff_approximate_the_gaussian_kernel_of_the_bandwidth(bandwidth):
    # With φ' = 2φ - 1 = cos(w·x + b): E[φ'(x) φ'(y)] = exp(-Σ (x-y)² / (2σ²)) / 2.
    basis = RandomFourierBasis(n_agents=2, state_dim=4, n_features=20_000,
                               bandwidth=bandwidth, seed=0)
    s = states((6,), n=2, d=4, lo=-0.6, hi=0.6, seed=2)
    p = 2 * basis(s).numpy() - 1
    sigma = np.tile(np.broadcast_to(np.asarray(bandwidth, float), (4,)), 2)
    x = s.reshape(6, 8) / sigma
    for i, j in itertools.product(range(6), repeat=2):
        kernel = np.exp(-0.5 * np.sum((x[i] - x[j]) ** 2))
        assert abs(np.mean(p[i] * p[j]) - 0.5 * kernel) < 0.02


def test_bases_read_demonstration_states():
    rng = np.random.default_rng(0)
    d = ContinuousDemonstrations(rng.uniform(-1, 1, (3, 5, 2, 4)), rng.normal(size=(3, 4, 2, 2)),
                                 np.array([4, 2, 3]))
    for basis in (PositionCellBasis(n_agents=2, **ARENA),
                  RandomFourierBasis(n_agents=2, state_dim=4),
                  ModuleBasis(module=bounded_mlp(8, 3), dim=3)):
        phi = basis(d.states)  # read-only arrays
        assert phi.shape == (3, 5, basis.dim)
        assert basis(d.states, d.states[..., :2]).shape == (3, 5, basis.dim)
