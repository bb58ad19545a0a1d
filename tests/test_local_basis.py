"""LocalReLUBasis (dicrl_torch.features.local): local ReLU units with exact zeros, built
without the game's obstacles, checked against a brute-force loop; a basis that can
express no constraint is refused before training."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from dicrl_torch.features.local import LocalReLUBasis, farthest_points

torch.set_num_threads(1)
BOX = [[-1.5, 1.5], [-1.5, 1.5]]


def _brute(basis: LocalReLUBasis, states: np.ndarray) -> np.ndarray:
    """Every feature by hand: polygonal norms as sums over the directions, units and
    rings one at a time."""
    dirs = basis.directions.numpy()
    norm = lambda v: sum(abs(float(d @ v)) for d in dirs)  # noqa: E731
    n, k = basis.n_agents, basis.n_centres
    out = np.zeros((len(states), basis.dim))
    for m, s in enumerate(states):
        for i in range(n):
            for j, c in enumerate(basis.centres.numpy()):
                value = max(0.0, 1.0 - norm(s[i, :2] - c) / float(basis.radii[j]))
                out[m, i * k + j if basis.per_agent else j] += value
        for r, (centre, width) in enumerate(zip(basis.rings.numpy(),
                                                basis.ring_widths.numpy(), strict=True)):
            for a in range(n):
                for b in range(a + 1, n):
                    gap = abs(norm(s[a, :2] - s[b, :2]) - centre)
                    out[m, len(basis.names) - basis.n_rings + r] += max(
                        0.0, 1.0 - gap / width)
    return out


@pytest.mark.parametrize("per_agent", [False, True])
def test_the_units_are_the_brute_force_loop(per_agent):
    basis = LocalReLUBasis(n_agents=3, bounds=BOX, n_centres=7, scales=(1, 2), n_rings=4,
                           directions=3, per_agent=per_agent, seed=2)
    states = np.random.default_rng(0).uniform(-1.5, 1.5, size=(40, 3, 4))
    phi = basis(torch.from_numpy(states)).numpy()
    np.testing.assert_allclose(phi, _brute(basis, states), atol=1e-12)
    assert basis.n_centres == 7 + 2  # 7 / 2² rounds to 2 coarse units, twice as wide
    assert basis.radii[7] > 1.5 * basis.radii[0]
    assert basis.dim == (27 if per_agent else 9) + 4
    assert phi.min() >= 0 and phi.max() <= basis.max_value
    assert (phi == 0).mean() > 0.3  # exact zeros outside the supports
    shares = basis.agent_shares().numpy()
    if per_agent:
        assert basis.names[10] == "agent1/local1" and shares[10].tolist() == [0, 1, 0]
    else:
        assert basis.names[1] == "local1" and np.allclose(shares[1], 1 / 3)
    assert basis.names[-1] == "ring3" and np.allclose(shares[-1], 1 / 3)


def test_the_rings_are_fine_near_zero_separation_and_stop_at_their_range():
    basis = LocalReLUBasis(n_agents=2, bounds=[[0, 4], [0, 6]], n_centres=3, n_rings=4)
    assert basis.ring_range == 2.0  # half the shorter side
    np.testing.assert_allclose(basis.rings.numpy(), [0, 0.125, 0.5, 1.125])
    np.testing.assert_allclose(basis.ring_widths.numpy(), [0.125, 0.375, 0.625, 0.875])
    states = np.zeros((3, 2, 4))
    states[:, 1, 0] = [0.0, 0.1, 2.5]  # separations 0, 0.1 and beyond the range
    rings = basis(torch.from_numpy(states)).numpy()[:, -4:]
    # each ring reaches to the next ring's centre: 1 - |s - c_r| / w_r
    np.testing.assert_allclose(rings[0], [1.0, 1 - 0.125 / 0.375, 1 - 0.5 / 0.625, 0.0])
    sep = float(basis._norm(torch.tensor([0.1, 0.0], dtype=torch.float64)))  # ν, ≈ 0.1
    np.testing.assert_allclose(rings[1], [1 - sep / 0.125, 1 - abs(sep - 0.125) / 0.375,
                                          1 - (0.5 - sep) / 0.625, 0.0])
    assert rings[2].sum() == 0  # nothing beyond the range


def test_a_unit_is_one_at_its_centre_and_zero_beyond_its_radius():
    basis = LocalReLUBasis(n_agents=2, bounds=BOX, n_centres=20, n_rings=0, seed=1)
    c = basis.centres.numpy()
    states = np.zeros((2, 2, 4))
    states[0, 0, :2], states[0, 1, :2] = c[0], c[0] + 10.0  # agent 1 outside the box
    phi = basis(torch.from_numpy(states)).numpy()
    assert phi[0, 0] == pytest.approx(1.0)
    # a point just beyond the polygon round centre 0, in every direction
    for angle in np.linspace(0, 2 * np.pi, 13):
        p = c[0] + 1.03 * basis.radius * np.array([math.cos(angle), math.sin(angle)])
        states[1, 0, :2] = p
        assert basis(torch.from_numpy(states)).numpy()[1, 0] == 0.0


def test_every_reachable_position_lies_in_some_support_and_the_polygon_is_round():
    basis = LocalReLUBasis(n_agents=1, bounds=[[0.0, 10.0], [0.0, 4.0]], n_centres=60,
                           n_rings=0, seed=5)
    states = np.zeros((20000, 1, 4))
    states[:, 0, :2] = np.random.default_rng(1).uniform([0, 0], [10, 4], size=(20000, 2))
    assert (basis(torch.from_numpy(states)).numpy() > 0).any(-1).all()
    v = torch.randn(1000, 2, dtype=torch.float64)
    ratio = basis._norm(v) / v.norm(dim=-1)
    assert 0.95 < float(ratio.min()) and float(ratio.max()) < 1.05  # a 12-gon


def test_farthest_points_spread_and_cover():
    pool = np.random.default_rng(0).uniform(0, 1, size=(2000, 2))
    pts, cover = farthest_points(pool, 25, np.random.default_rng(1))
    d = np.linalg.norm(pts[:, None] - pts[None], axis=-1) + np.eye(25) * 9
    nearest = np.linalg.norm(pool[:, None] - pts[None], axis=-1).min(1)
    assert cover == pytest.approx(nearest.max())
    assert d.min() >= cover - 1e-12  # greedy: every chosen point at least that far apart
    with pytest.raises(ValueError, match="1 <= k <= 2000"):
        farthest_points(pool, 0, np.random.default_rng(0))


@pytest.mark.parametrize("per_agent", [True, False])
def test_dilated_grows_the_supports_and_dot_keeps_only_the_weighted_units(per_agent):
    basis = LocalReLUBasis(n_agents=2, bounds=[[0, 10], [0, 10]], n_centres=30, n_rings=8,
                           per_agent=per_agent, agent_prefix="drone", seed=0)
    states = np.random.default_rng(3).uniform(0, 10, size=(300, 2, 4))
    wide = basis.dilated(0.5)
    assert wide.radius == pytest.approx(basis.radius + 0.5) and basis.dilatable
    narrow, grown = basis.numpy_features(states) > 0, wide.numpy_features(states) > 0
    assert (grown | ~narrow).all() and grown.sum() > narrow.sum()
    w = np.zeros(basis.dim)
    w[[1, 5, 37, basis.dim - 8, basis.dim - 3]] = [0.7, 0.5, 0.8, 0.6, 0.9]
    np.testing.assert_allclose(basis.dot(states, w), basis.numpy_features(states) @ w,
                               atol=1e-12)
    # the planner's batches: positions beyond the box too, every unit weighted, grown
    outside = np.random.default_rng(4).uniform(-1, 11, size=(2000, 2, 4))
    dense = np.random.default_rng(5).uniform(0, 1, basis.dim)
    for b in (basis, wide):
        np.testing.assert_allclose(b.dot(outside, dense), b.numpy_features(outside) @ dense,
                                   atol=1e-12)
    assert np.all(basis.dot(states, np.zeros(basis.dim)) == 0)
    with pytest.raises(ValueError, match="margin"):
        basis.dilated(-1.0)


def _compose(*overrides):
    from pathlib import Path

    configs = Path(__file__).resolve().parents[1] / "configs"
    with initialize_config_dir(config_dir=str(configs), version_base=None):
        return compose(config_name="train", overrides=list(overrides))


@pytest.mark.parametrize(("experiment", "cost", "moved"), [
    ("mpe_quick", "local_relu", ["env.layout.disc_centre=[0.6,-0.4]",
                                 "env.layout.disc_radius=0.5"]),
    ("table2_quick", "local_relu_drones", ["env.arena.dynamics.max_speed=1.2"]),
])
def test_the_weights_know_nothing_of_the_obstacles(experiment, cost, moved):
    """The shipped configs build the same weights whatever the obstacle (the MPE disc
    moved and grown; the drones' obstacles are fixed, so their dynamics change instead)."""
    from common import build

    a = build(_compose(f"experiment={experiment}", f"features/cost={cost}").features.cost)
    b = build(_compose(f"experiment={experiment}", f"features/cost={cost}",
                       *moved).features.cost)
    assert isinstance(a, LocalReLUBasis)
    sa, sb = a.state_dict(), b.state_dict()
    assert sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)
    assert a.radius == b.radius and a.ring_range == b.ring_range


def test_settings_are_checked():
    for kwargs, match in [({"n_centres": 0}, "n_centres"), ({"overlap": 0.5}, "overlap"),
                          ({"per_agent": 1}, "per_agent"), ({"bounds": [[1, 0], [0, 1]]},
                                                           "bounds"),
                          ({"n_rings": -1}, "n_rings"), ({"directions": 0}, "directions")]:
        with pytest.raises(ValueError, match=match):
            LocalReLUBasis(**{"n_agents": 2, "bounds": BOX, **kwargs})
