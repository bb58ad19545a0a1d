"""Region scores (dicrl_torch.region): the learned set as a classifier of joint states,
checked against hand counts, the games' own violation checks and brute-force geometry."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dicrl_torch.envs.drones import DroneDynamics, joint_step
from dicrl_torch.region import (
    RegionTruth,
    feature_support,
    predicted_forbidden,
    recall_bound,
    region_scores,
    undetermined_states,
)

torch.set_num_threads(1)


# ------------------------------------------------------------------ the scores
def test_region_scores_are_the_hand_counts():
    forbidden = np.array([1, 1, 0, 0, 0, 0], dtype=bool)
    predicted = np.array([1, 0, 1, 1, 0, 0], dtype=bool)
    undetermined = np.array([0, 0, 1, 0, 0, 1], dtype=bool)
    s = region_scores(forbidden, predicted, undetermined)
    assert s["recall"] == 1 / 2
    assert s["precision"] == 1 / 3  # 1 of 3 predicted is forbidden
    assert s["precision_determined"] == 1 / 2  # state 2 set apart: 1 of {0, 3}
    assert s["iou"] == 1 / 4  # {0} over {0, 1, 2, 3}
    assert s["undetermined"] == 1 / 3
    none = np.zeros(6, dtype=bool)
    empty = region_scores(forbidden, none, undetermined)
    assert empty["recall"] == 0.0 and empty["precision"] == 1.0 and empty["iou"] == 0.0
    with pytest.raises(ValueError, match="undetermined states must be free"):
        region_scores(forbidden, predicted, forbidden)
    with pytest.raises(ValueError, match="one length"):
        region_scores(forbidden, predicted[:5], undetermined)


class Boxes(torch.nn.Module):
    """Feature k: 1 where agent 0's x lies in [k, k + 1) (a toy basis with exact zeros)."""

    dim = 3

    def forward(self, states):
        x = states[..., 0, 0]
        return torch.stack([((x >= k) & (x < k + 1)).double() for k in range(3)], -1)


def _states(xs) -> np.ndarray:
    s = np.zeros((len(xs), 2, 4))
    s[:, 0, 0] = xs
    s[:, 1, 0] = 10.0  # agent 1 far away
    return s


def test_support_prediction_and_the_recall_bound_by_hand():
    states = _states([0.5, 1.5, 2.5, 2.7, 5.0])
    support = feature_support(Boxes(), states)
    assert support.tolist() == [[1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, 1], [0, 0, 0]]
    assert predicted_forbidden(support, np.array([0, 0, 1], bool)).tolist() == [
        0, 0, 1, 1, 0]
    with pytest.raises(ValueError, match=r"\[3\] bool mask"):
        predicted_forbidden(support, np.array([1, 0], bool))
    forbidden = np.array([0, 1, 1, 1, 1], dtype=bool)  # x >= 1
    # The demonstrations use feature 1 (they fly through [1, 2)), the starts feature 0:
    # only feature 2 can become a constraint, covering 2 of the 4 forbidden states.
    usable = ~(feature_support(Boxes(), _states([1.2, 0.1])).any(0))
    assert usable.tolist() == [False, False, True]
    assert recall_bound(support, forbidden, usable) == 2 / 4
    assert recall_bound(support, forbidden, np.array([False, True, True])) == 3 / 4
    assert recall_bound(support, np.zeros(5, bool), usable) == 1.0


def test_undetermined_states_come_from_the_demonstrations():
    """Two agents flying parallel lanes y = 0 and y = 1 in steps of 0.1: a free state
    with an agent 0.5 from every lane point, or closer together than 1.0, is undetermined;
    one on the lanes 1.0 apart is not; a forbidden one never is."""
    xs = np.arange(0.0, 1.01, 0.1)
    episode = np.zeros((len(xs), 2, 4))
    episode[:, 0, 0], episode[:, 1, 0], episode[:, 1, 1] = xs, xs, 1.0
    test = np.zeros((4, 2, 4))
    test[0, :, :2] = [[0.5, 0.0], [0.5, 1.0]]    # on the lanes, 1.0 apart
    test[1, :, :2] = [[0.5, 0.5], [0.5, 1.0]]    # agent 0 between the lanes
    test[2, :, :2] = [[0.5, 0.0], [0.55, 0.0]]   # both on lane 0: 0.05 apart
    test[3, :, :2] = [[0.5, 0.5], [0.5, 1.0]]    # as 1, but forbidden
    free = np.array([True, True, True, False])
    und, band = undetermined_states(test, free, [episode])
    assert band["step"] == pytest.approx(0.1) and band["min_separation"] == 1.0
    assert und.tolist() == [False, True, True, False]
    with pytest.raises(ValueError, match="at least one demonstration"):
        undetermined_states(test, free, [])


def test_test_states_cover_the_box_and_the_speeds_seeded():
    truth = RegionTruth(forbidden=lambda s: np.zeros(len(s), bool), low=(-1.0, 0.0),
                        high=(1.0, 2.0), max_speed=1.5, n_agents=3)
    s = truth.test_states(5000, seed=3)
    assert s.shape == (5000, 3, 4)
    assert (s[..., 0] >= -1).all() and (s[..., 0] <= 1).all()
    assert (s[..., 1] >= 0).all() and (s[..., 1] <= 2).all()
    speed = np.linalg.norm(s[..., 2:], axis=-1)
    assert speed.max() <= 1.5 and speed.max() > 1.4
    assert s[..., 0].min() < -0.99 and s[..., 1].max() > 1.99  # the whole box
    np.testing.assert_array_equal(s, truth.test_states(5000, seed=3))
    assert not np.array_equal(s, truth.test_states(5000, seed=4))


# ------------------------------------------------------------------ the games
def test_the_mpe_truth_is_the_geometry():
    """MPETask.region_truth: an agent within the disc's radius of its centre, or two
    agents closer than the minimum distance, by brute force over random states."""
    from test_mpe_task import tiny_task

    task = tiny_task()
    truth, lay = task.region_truth(), task.layout
    states = truth.test_states(3000, seed=0)
    want = np.zeros(len(states), dtype=bool)
    for m, s in enumerate(states):
        for i in range(lay.n_agents):
            if np.hypot(*(s[i, :2] - lay.disc_centre)) < lay.disc_radius:
                want[m] = True
            for j in range(i):
                if np.hypot(*(s[i, :2] - s[j, :2])) < lay.min_distance:
                    want[m] = True
    np.testing.assert_array_equal(truth.forbidden(states), want)
    assert 0.05 < want.mean() < 0.3  # both kinds occur


def test_the_drone_truth_is_the_games_own_violation_check():
    """DroneTask.region_truth equals joint_step's violated flags for drones at rest
    given no command (they stay where they are), over random states."""
    from common import drone_task
    from test_drone_dicrl import _compose

    task = drone_task(_compose("eval_episodes=2"))
    truth = task.region_truth()
    states = truth.test_states(3000, seed=1)
    at_rest = states.copy()
    at_rest[..., 2:] = 0.0
    step = joint_step(at_rest, np.zeros((len(states), 2, 2)), np.ones((len(states), 2), bool),
                      dynamics=DroneDynamics())
    np.testing.assert_array_equal(step.state[..., :2], at_rest[..., :2])
    np.testing.assert_array_equal(truth.forbidden(states), step.violated.any(-1))
    assert 0.02 < truth.forbidden(states).mean() < 0.5  # the block, the proximity
    # The hand-made cells on the true set: the obstacles are unions of cells and the
    # proximity feature is the proximity rule, so the truth's features cover the
    # forbidden region exactly, and no free state is predicted.
    row = task.region_rates(task.true)
    assert row["region_recall"] == 1.0 and row["region_precision"] == 1.0
    assert row["region_iou"] == 1.0
    nothing = task.region_rates(np.zeros_like(task.true))
    assert nothing["region_recall"] == 0.0 and nothing["region_precision"] == 1.0


def test_mpe_cells_on_the_true_set_cover_the_disc_with_free_space_round_it():
    """The 4 cells overlapping the disc and the proximity feature: every forbidden state
    is predicted (recall 1), and the cells' corners outside the disc are predicted too
    (precision < 1); set apart, the undetermined ones raise the precision."""
    from test_mpe_task import tiny_task

    task = tiny_task()
    row = task.rates(task.true)
    assert row["region_recall"] == 1.0
    assert 0.5 < row["region_precision"] < 1.0
    assert row["region_precision_determined"] >= row["region_precision"]
    assert 0.0 < row["region_undetermined"] < 1.0
    test = task.region_test()
    assert test["states"].shape == (task.region_test_states, 2, 4)
    assert test["band"]["min_separation"] > task.layout.min_distance  # the experts' margin
