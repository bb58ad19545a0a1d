"""The Fig. 2 analogues (dicrl_torch.figures) and the per-outer-iteration metrics that
experiments/train.py records for them in results.json's history."""

from __future__ import annotations

import json

import matplotlib.image
import numpy as np
import pytest
from test_configs import run_train  # the tiny end-to-end run (TINY: 2 learners)
from tiny_dicrl import build_tiny
from tiny_train import compose_train

from dicrl_torch.envs.grid import GridLayout
from dicrl_torch.figures import (
    CURVES_FIGSIZE,
    DPI,
    constraint_cells,
    metric_curves,
    obstacle_cells,
    side_by_side,
    state_visitation,
    visitation_heatmap,
)
from dicrl_torch.solvers.experts import sample_trajectories

LAYOUT = GridLayout.open_grid(5, 1)  # no obstacles; start (0, 4), goal (4, 4)
LEFT, RIGHT = LAYOUT.cell((1, 1)), LAYOUT.cell((3, 1))  # free cells in one row


def staying_at(cell: int, m: int = 3, horizon: int = 4) -> np.ndarray:
    """Demonstration states ``[m, T+1, 1]`` of an expert that never leaves ``cell``."""
    return np.full((m, horizon + 1, 1), cell, dtype=np.int64)


def red_pixels(img: np.ndarray) -> np.ndarray:
    """``[H, W]`` mask of the constraint crosses' red (no viridis colour is red)."""
    r, g, b = (img[..., k].astype(int) for k in range(3))
    return (r > 200) & (g < 80) & (b < 80)


# ---------------------------------------------------------------------- visitation
def test_state_visitation_by_hand():
    # m = 2 trajectories of N = 2 experts over 4 cells, T = 2
    states = np.array([[[0, 2], [1, 2], [1, 3]],
                       [[0, 2], [0, 3], [0, 3]]])
    # share of the 4 expert trajectories that enter each cell
    np.testing.assert_allclose(state_visitation(states, 4), [0.5, 0.25, 0.5, 0.5])
    # discounted steps (t = 0, 1: the decision states), per expert trajectory
    np.testing.assert_allclose(state_visitation(states, 4, gamma=0.5),
                               [2.5 / 4, 0.5 / 4, 2.5 / 4, 0.5 / 4])
    with pytest.raises(ValueError, match=r"\[m, T\+1, N\]"):
        state_visitation(states[0], 4)
    with pytest.raises(ValueError, match="outside"):
        state_visitation(states, 3)
    with pytest.raises(ValueError, match="gamma"):
        state_visitation(states, 4, gamma=1.5)


def test_discounted_visitation_matches_the_solver_occupancy():
    """The docstring's claim: sampled trajectories' discounted visitation estimates
    ``local_occupancy.sum(2).mean(0)`` of the policy they are sampled from."""
    solver, rb, _, _ = build_tiny()
    sol = solver.solve(rb().weighted(rb.true_weights()), temperature=1.0, forward=True)
    demos = sample_trajectories(sol, 4000, np.random.default_rng(1))
    empirical = state_visitation(demos.states, solver.model.n_cells, gamma=solver.model.gamma)
    np.testing.assert_allclose(empirical, sol.local_occupancy.sum(2).mean(0).numpy(), atol=0.03)


def test_heatmap_colours_the_visited_cell():
    a = visitation_heatmap(LAYOUT, state_visitation(staying_at(LEFT), LAYOUT.n_cells))
    b = visitation_heatmap(LAYOUT, state_visitation(staying_at(RIGHT), LAYOUT.n_cells))
    assert a.shape == b.shape and a.dtype == np.uint8 and a.shape[2] == 3
    # the same colour scale (0..1) in both: only the two cells differ, and the visited
    # one is the bright end of viridis in each image
    diff = np.abs(a.astype(int) - b.astype(int)).sum(2) > 60
    ys, xs = np.nonzero(diff)
    assert len(xs) > 100
    mid = (xs.min() + xs.max()) / 2
    left, right = diff & (np.arange(a.shape[1]) < mid), diff & (np.arange(a.shape[1]) > mid)
    assert 0.7 < left.sum() / right.sum() < 1.4  # two cells of the same size
    brightness = lambda img, mask: img[mask].astype(int).sum(1).mean()  # noqa: E731
    assert brightness(a, left) > brightness(a, right) + 150
    assert brightness(b, right) > brightness(b, left) + 150


def test_constraint_crosses_are_drawn_on_their_cells():
    visits = state_visitation(staying_at(LEFT), LAYOUT.n_cells)
    plain = visitation_heatmap(LAYOUT, visits)
    crossed = visitation_heatmap(LAYOUT, visits, constraint_cells=[LEFT])
    assert not red_pixels(plain).any()
    ys, xs = np.nonzero(red_pixels(crossed))
    assert len(xs) > 20
    # the cross's centre lies in the cell the heat map colours
    other = visitation_heatmap(LAYOUT, state_visitation(staying_at(RIGHT), LAYOUT.n_cells))
    cy, cx = np.nonzero(np.abs(plain.astype(int) - other.astype(int)).sum(2) > 60)
    in_left = cx < (cx.min() + cx.max()) / 2
    assert cx[in_left].min() < xs.mean() < cx[in_left].max()
    assert cy[in_left].min() < ys.mean() < cy[in_left].max()


def test_true_obstacles_are_marked():
    layout = GridLayout.scobee(1)
    cells = obstacle_cells(layout)
    assert cells == sorted(layout.cell(c) for c in layout.obstacles) and cells
    visits = np.zeros(layout.n_cells)
    assert red_pixels(visitation_heatmap(layout, visits, constraint_cells=cells)).sum() > \
        10 * len(cells)
    with pytest.raises(ValueError, match="one finite value >= 0 per cell"):
        visitation_heatmap(layout, visits[:-1])


def test_constraint_cells_of_feature_names():
    names = ["cell(1,0)", "expert1/cell(0,2)", "action NE", "collision", "f3", "cell(1,0)"]
    assert constraint_cells(LAYOUT, names) == [LAYOUT.cell((1, 0)), LAYOUT.cell((0, 2))]
    with pytest.raises(ValueError, match="outside the 5x5 grid"):
        constraint_cells(LAYOUT, ["cell(7,0)"])
    # A region feature stands for all its cells (RegionIndicatorCostBasis.region_cells).
    assert constraint_cells(LAYOUT, ["region wall", "cell(0,0)"],
                            {"region wall": (7, 12)}) == [0, 7, 12]
    assert constraint_cells(LAYOUT, ["region wall"]) == []


def test_side_by_side_pads_with_white():
    img = side_by_side([np.zeros((3, 2, 3), np.uint8), np.zeros((5, 4, 3), np.uint8)])
    assert img.shape == (5, 6, 3) and (img[3:, :2] == 255).all() and (img[:, 2:] == 0).all()


# ---------------------------------------------------------------------- metric curves
def history(n: int = 4, learners: int = 2, fpr: float = 0.2, evaluated=(0, 3)) -> list[dict]:
    """A results.json-like history: FPR/FNR/RFD every outer iteration, CR/CVR at
    ``evaluated``."""
    out = []
    for k in range(n):
        e = {"outer_iteration": k, "multiplier": [-1.0] * learners,
             "FPR": [fpr] * learners, "FNR": [1 - k / n] * learners,
             "RFD": [0.5 / (k + 1) + 0.01 * v for v in range(learners)]}
        if k in evaluated:
            e.update(CR=[10.0 * k] * learners, CVR=[0.5 / (k + 1)] * learners)
        out.append(e)
    return out


ROW = {"CR_mean": 30.0, "FPR": 0.1, "FNR": 0.3, "CVR": 0.01, "RFD": 0.2}


def test_metric_curves_draws_every_input():
    base = metric_curves({"D-ICRL": history(), "C-ICRL": history(learners=1)})
    w, h = CURVES_FIGSIZE
    assert base.shape == (round(h * DPI), round(w * DPI), 3) and base.dtype == np.uint8
    # other values, reference lines, final table markers: each changes the image
    for kwargs in ({"histories": {"D-ICRL": history(fpr=0.9), "C-ICRL": history(learners=1)}},
                   {"baselines": {"ME-greedy": ROW}},
                   {"experts": {"Experts (nominal)": {**ROW, "FPR": None, "FNR": None}}},
                   {"final_rows": {"D-ICRL": [ROW, ROW]}}):
        kwargs.setdefault("histories", {"D-ICRL": history(), "C-ICRL": history(learners=1)})
        assert (metric_curves(**kwargs) != base).any(), kwargs


def test_metric_curves_refuses_bad_histories():
    broken = history()
    broken[2]["RFD"] = broken[2]["RFD"][:1]  # one learner's value missing
    with pytest.raises(ValueError, match="mismatched lengths: outer iteration 2 holds 1 'RFD'"):
        metric_curves({"D-ICRL": broken})
    old = history()
    del old[1]["FPR"]  # a results.json from before the per-iteration metrics
    with pytest.raises(ValueError, match="no 'FPR' at outer iteration 1.*rerun"):
        metric_curves({"D-ICRL": old})
    greedy = [{"step": 0, "FPR": 0.0, "FNR": 1.0}, {"step": 1, "FPR": 0.0, "FNR": 0.5}]
    with pytest.raises(ValueError, match="baselines="):
        metric_curves({"ME-greedy": greedy})
    with pytest.raises(ValueError, match="in order"):
        metric_curves({"D-ICRL": history()[::-1]})
    with pytest.raises(ValueError, match="at least one"):
        metric_curves({})
    with pytest.raises(ValueError, match="empty"):
        metric_curves({"D-ICRL": []})


# ---------------------------------------------------------------------- train.py
def test_eval_every_is_checked():
    import config_checks  # experiments/ is on pytest's pythonpath
    with pytest.raises(config_checks.ConfigError, match="eval_every=0 is invalid"):
        config_checks.check_config(compose_train("eval_every=0"))
    config_checks.check_config(compose_train("eval_every=1"))


def test_tiny_run_records_the_curves_and_writes_the_figures(tmp_path):
    out = run_train(tmp_path, "algo.outer_iterations=5", "eval_every=3", "logger=tensorboard")
    assert out.returncode == 0, out.stderr[-3000:]
    res = json.loads((tmp_path / "results.json").read_text())
    for method, n_learners in (("D-ICRL", 2), ("C-ICRL", 1)):
        hist = res["history"][method]
        assert [h["outer_iteration"] for h in hist] == [0, 1, 2, 3, 4]
        for h in hist:
            for key in ("FPR", "FNR", "RFD"):
                assert len(h[key]) == n_learners and all(0 <= x for x in h[key]), (method, key)
        # CR/CVR after the first, every 3rd and the last outer iteration
        assert [h["outer_iteration"] for h in hist if "CR" in h] == [0, 2, 4]
        assert all(len(h["CR"]) == len(h["CVR"]) == n_learners for h in hist if "CR" in h)
        for i, row in enumerate(res["methods"][method]["learners"]):
            # the last iteration's values are the table's before pruning
            assert hist[-1]["FPR"][i] == row["FPR_before_pruning"]
            assert hist[-1]["FNR"][i] == row["FNR_before_pruning"]
            assert hist[-1]["RFD"][i] == row["RFD"]
            assert isinstance(row["constraints"], list)
    for name in ("fig2a_true_visitation", "fig2b_learned_constraints",
                 "fig2c-g_metric_curves"):
        path = tmp_path / f"{name}.png"
        assert matplotlib.image.imread(path).ndim == 3 and str(path) in out.stdout
    assert (tmp_path / "tb" / "figures").is_dir()
