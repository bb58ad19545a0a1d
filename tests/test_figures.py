"""The Fig. 2 analogues (dicrl_torch.figures) and the per-outer-iteration metrics that
experiments/train.py records for them in results.json's history."""

from __future__ import annotations

import json

import matplotlib.image
import numpy as np
import pytest
import torch
from test_configs import run_train  # the tiny end-to-end run (TINY: 2 learners)
from tiny_dicrl import build_tiny
from tiny_train import compose_train

from dicrl_torch.algos.identifiability import Identifiability
from dicrl_torch.envs.grid import GridLayout, TabularGridModel
from dicrl_torch.envs.gridworld_env import render_grid
from dicrl_torch.features.bases import GoalClosenessRewardBasis, SharedIndicatorCostBasis
from dicrl_torch.figures import (
    CLASS_COLOURS,
    CURVES_FIGSIZE,
    DPI,
    constraint_cells,
    cost_weight_curves,
    identifiability_cells,
    identifiability_figure,
    identifiability_legend,
    identifiability_map,
    metric_curves,
    obstacle_cells,
    side_by_side,
    state_visitation,
    tiled,
    visitation_heatmap,
)
from dicrl_torch.runs.grid import GridTask
from dicrl_torch.solvers.experts import sample_trajectories
from dicrl_torch.solvers.factored import FactoredSoftBellman

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


def weight_history(n_features: int = 4, learners: int = 2) -> list[dict]:
    """Three outer iterations: feature 0 rises to 0.9, the rest stay at 0.1."""
    return [{"outer_iteration": n, "cost_weights": [[0.3 * (n + 1)] + [0.1] * (n_features - 1)
                                                    for _ in range(learners)]}
            for n in range(3)]


def _reddish(img: np.ndarray) -> int:
    r, g, b = (img[..., k].astype(int) for k in range(3))
    return int(((r > 180) & (g < 90) & (b < 90)).sum())


def test_cost_weight_curves_draw_true_features_red_and_skip_methods_without_weights():
    true = np.array([True, False, False, False])
    img = cost_weight_curves({"D-ICRL": weight_history(), "C-ICRL": weight_history(learners=1),
                              "ME-greedy": [{"step": 0, "FPR": 0.0}]}, true=true,
                             threshold=0.5)
    assert img.dtype == np.uint8 and img.ndim == 3
    assert img.shape[1] == round(3 * 4.2 * DPI)  # three learners' panels, greedy left out
    grey = cost_weight_curves({"D-ICRL": weight_history()}, true=None)
    assert _reddish(img) > 0 and _reddish(grey) == 0
    # another weight moves the picture
    moved = weight_history()
    moved[1]["cost_weights"][0][2] = 0.8
    assert (cost_weight_curves({"D-ICRL": moved}) != cost_weight_curves(
        {"D-ICRL": weight_history()})).any()


def test_cost_weight_curves_refuse_what_they_cannot_draw():
    with pytest.raises(ValueError, match="cost_weights.*rerun"):
        cost_weight_curves({"D-ICRL": [{"outer_iteration": 0, "FPR": [0.0]}]})
    with pytest.raises(ValueError, match="true has .* 4 cost weights"):
        cost_weight_curves({"D-ICRL": weight_history()}, true=[True, False])


# ---------------------------------------------------------------------- train.py
def test_metrics_against_bytes_needs_the_counts():
    from dicrl_torch.figures import metrics_against_bytes

    history = [{"outer_iteration": n, "FPR": [0.1, 0.2], "FNR": [0.0, 0.0],
                "CR": None if n else [1.0, 2.0], "CVR": None if n else [0.0, 0.1],
                "bytes_sent": [1000 * (n + 1), 900 * (n + 1)]} for n in range(3)]
    img = metrics_against_bytes({"exact": history, "int8": history}, title="t")
    assert img.ndim == 3 and img.dtype == np.uint8
    with pytest.raises(ValueError, match="no 'bytes_sent'"):
        metrics_against_bytes({"old": [{"outer_iteration": 0, "FPR": [0.1]}]})


def test_eval_every_is_checked():
    import common  # experiments/ is on pytest's pythonpath
    import config_checks
    with pytest.raises(config_checks.ConfigError, match="eval_every=0 is invalid"):
        common.check_config(compose_train("eval_every=0"))
    common.check_config(compose_train("eval_every=1"))


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
    # each D-learner's traffic: its row's total is its history's last count and the
    # certificate's gathers to the other learner (the bitmask of d cost features in
    # 52-bit words; the reward weights of η̄, 2 per expert, and of its shard's own fit)
    d = len(res["history"]["D-ICRL"][-1]["cost_weights"][0])
    rewards = 1 + bool(res["config"]["algo"]["certificate"]["shard_fits"])
    reward_dim = rewards * 2 * res["config"]["env"]["layout"]["n_experts"]
    for i, row in enumerate(res["methods"]["D-ICRL"]["learners"]):
        sent = [h["bytes_sent"][i] for h in res["history"]["D-ICRL"]]
        assert sent == sorted(sent) and sent[0] > 0
        total = row["traffic"]["algorithm_bytes_sent"]
        assert total == 1000 * row["KB_sent"]
        assert total - sent[-1] == 8 * (-(-d // 52) + reward_dim)
    assert "KB_sent" in out.stdout
    for name in ("fig2a_true_visitation", "fig2b_learned_constraints",
                 "fig2c-g_metric_curves", "identifiability_classes", "traffic"):
        path = tmp_path / f"{name}.png"
        assert matplotlib.image.imread(path).ndim == 3 and str(path) in out.stdout
    assert (tmp_path / "tb" / "figures").is_dir()


# ---------------------------------------------------------------------- identifiability
# 4x4, one expert; true constraints: three obstacle cells and the action NE
WALLED = GridLayout(size=4, starts=((0, 3),), goals=((3, 3),),
                    obstacles=((1, 1), (2, 1), (1, 2)), forbidden_actions=("NE",))
CLASSES = {"demonstrated": ["cell(1,1)"], "required": ["cell(2,1)", "action NE"],
           "undetermined": ["cell(1,2)"]}


def colour_mask(img: np.ndarray, cls: str) -> np.ndarray:
    """``[H, W]`` pixels of ``cls``'s colour."""
    rgb = [int(CLASS_COLOURS[cls][k:k + 2], 16) for k in (1, 3, 5)]
    return (np.abs(img.astype(int) - rgb) <= 2).all(2)


def test_identifiability_cells_by_hand():
    cells, off = identifiability_cells(WALLED, {**CLASSES, "n_required": 2})
    at = WALLED.cell
    assert cells == {at((1, 1)): "demonstrated", at((2, 1)): "required",
                     at((1, 2)): "undetermined"}
    assert off == {"action NE": "required"}
    # a region stands for its cells; per-expert features of one cell that differ: mixed
    cells, off = identifiability_cells(
        WALLED, {"required": ["region wall", "expert0/cell(3,0)", "collision"],
                 "undetermined": ["expert1/cell(3,0)"]}, {"region wall": (0, 1)})
    assert cells == {0: "required", 1: "required", at((3, 0)): "mixed"}
    assert off == {"collision": "required"}


def cell_centre(layout: GridLayout, cell: int, title: str) -> tuple[int, int]:
    """``(row, column)`` pixel of ``cell``'s centre in render_grid's image with ``title``:
    the centre of its cross there."""
    ys, xs = np.nonzero(red_pixels(render_grid(layout, constraint_cells=[cell], title=title)))
    return round(ys.mean()), round(xs.mean())


def test_identifiability_map_colours_each_cell_by_its_class():
    cells, off = identifiability_cells(WALLED, CLASSES)
    img = identifiability_map(WALLED, cells, title="classes")
    assert img.shape == render_grid(WALLED, title="classes").shape and img.dtype == np.uint8
    pitch = cell_centre(WALLED, 1, "classes")[1] - cell_centre(WALLED, 0, "classes")[1]
    for cell, cls in cells.items():
        y, x = cell_centre(WALLED, cell, "classes")
        assert colour_mask(img[y - 5:y + 6, x - 5:x + 6], cls).all(), cls
        # the whole cell, and no other
        assert 0.85 * pitch ** 2 < colour_mask(img, cls).sum() < 1.15 * pitch ** 2, cls
    y, x = cell_centre(WALLED, WALLED.cell((2, 2)), "classes")
    assert (img[y, x] == 255).all()  # a free cell stays white
    # learned crosses on top of the colours
    crossed = identifiability_map(WALLED, cells, constraint_cells=list(cells), title="classes")
    assert red_pixels(crossed).sum() > 3 * 20
    with pytest.raises(ValueError, match="unknown identifiability classes"):
        identifiability_map(WALLED, {0: "probable"})
    legend = identifiability_legend(off)
    assert legend.shape[0] == img.shape[0] and colour_mask(legend, "required").any()
    mixed = identifiability_legend(off, mixed=True)  # its patch only when asked
    assert colour_mask(mixed, "mixed").sum() > colour_mask(legend, "mixed").sum() + 50


def test_identifiability_titles_fit_their_panels():
    # long names of features without a cell (per-expert actions of 3 experts, false ones)
    actions = [f"expert{i}/action {a}" for i in range(3) for a in ("NE", "NW")]
    classes = {"required": ["cell(2,1)", *actions, "collision"], "undetermined": ["cell(1,2)"]}
    rows = {"D-ICRL learner 1": {"constraints": ["cell(2,1)", *actions, "collision",
                                                "expert2/action SE", "expert0/action SW"],
                                "FPR": 0.125, "FNR": None, "FNR_required": 0.0},
            "C-ICRL": {"constraints": []}}
    img = identifiability_figure(WALLED, classes, rows, max_width=10_000)
    w, legend = render_grid(WALLED, title="x").shape[1], identifiability_legend({}).shape[1]
    assert img.shape[1] == 3 * w + legend
    for x in (0, w + legend, 2 * w + legend):  # the classes' panel, then the learners'
        panel = img[:, x:x + w]
        assert (panel[:, :3] == 255).all() and (panel[:, -3:] == 255).all(), x  # no clipping
        assert (panel[:40] < 128).any(2).sum() > 200, x  # a title is there


def test_tiled_wraps_wide_rows():
    ims = [np.zeros((3, 4, 3), np.uint8), np.zeros((5, 4, 3), np.uint8),
           np.zeros((2, 4, 3), np.uint8)]
    assert tiled(ims, max_width=100).shape == (5, 12, 3)
    img = tiled(ims, max_width=9)  # two rows: 3 + 5 high, then 2 high padded to 8 wide
    assert img.shape == (7, 8, 3) and (img[5:, 4:] == 255).all() and (img[5:, :4] == 0).all()


def walled_task() -> GridTask:
    model = TabularGridModel(layout=WALLED, horizon=6, gamma=0.95)
    rb = GoalClosenessRewardBasis(model)
    return GridTask(layout=WALLED, model=model,
                    solver=FactoredSoftBellman(model=model, dtype=torch.float64),
                    reward_basis=rb, cost_basis=SharedIndicatorCostBasis(model),
                    true_reward_weights=rb.true_weights(), split=[2, 3], seed=0,
                    eval_episodes=2, constraint_rule="threshold")


def hand_made_identifiability(names: list[str]) -> Identifiability:
    def mask(members):
        return torch.tensor([n in members for n in names])
    scope = mask([n for c in CLASSES.values() for n in c])
    return Identifiability(names=names, scope=scope, demonstrated=mask(CLASSES["demonstrated"]),
                           required=mask(CLASSES["required"]),
                           undetermined=mask(CLASSES["undetermined"]),
                           probability=torch.full((len(names),), float("nan")),
                           infeasible=mask([]))


def test_grid_task_draws_the_identifiability_classes():
    task = walled_task()
    row = {"CR_mean": 1.0, "FPR": 0.5, "FNR": None, "FNR_required": 0.0,
           "constraints": ["cell(2,1)", "cell(0,0)", "action NE"]}
    methods = {"D-ICRL": {"learners": [row, row]}, "C-ICRL": {"learners": [row]},
               "Experts (nominal)": {"learners": [{"CR_mean": 2.0}]}}
    kw = dict(methods=methods, histories={"D-ICRL": history(), "C-ICRL": history(learners=1)},
              experiment="test", eval_every=1)
    task.identifiability = lambda: hand_made_identifiability(list(task.cost_basis.names))
    img = task.figures(**kw)["identifiability_classes"]
    h, w, _ = render_grid(WALLED, title="x").shape
    # the classes, their legend, then D-ICRL learner 1, 2 and C-ICRL in one row
    assert img.shape == (h, 4 * w + identifiability_legend({}).shape[1], 3)
    for cls in ("demonstrated", "required", "undetermined"):
        assert colour_mask(img[:, :w], cls).sum() > 100, cls  # the classes' panel
        assert colour_mask(img[:, -w:], cls).sum() > 100, cls  # the last learner's
    assert red_pixels(img[:, -w:]).sum() > 2 * 20  # its learned cells crossed
    task.identifiability = lambda: None  # no ground truth, or not every demonstration
    images = task.figures(**kw)
    assert "identifiability_classes" not in images and "fig2b_learned_constraints" in images
