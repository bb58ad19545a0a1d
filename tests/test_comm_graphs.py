"""Mixing schedules and the checks of the paper's Assumptions 1–3 (Section 2)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dicrl_torch.comm import (
    CompleteSchedule,
    DirectedCycleSchedule,
    GraphAssumptionError,
    MatrixSchedule,
    MixingSchedule,
    RingSchedule,
    TimeVaryingSchedule,
    check_inner_schedule,
    check_outer_schedule,
)

SIZES = [1, 2, 3, 4, 7]
FACTORIES = {
    "complete": lambda n: CompleteSchedule(n_learners=n),
    "ring": lambda n: RingSchedule(n_learners=n),
    "ring_heavy_self": lambda n: RingSchedule(n_learners=n, self_weight=0.8),
    "directed_cycle": lambda n: DirectedCycleSchedule(n_learners=n),
    "time_varying": lambda n: TimeVaryingSchedule(n_learners=n),
    "time_varying_B3": lambda n: TimeVaryingSchedule(n_learners=n, period=3, seed=4),
    "time_varying_B9": lambda n: TimeVaryingSchedule(n_learners=n, period=9, self_weight=0.3),
}
ALL = [(name, n) for name in FACTORIES for n in SIZES]


def make(name: str, n: int) -> MixingSchedule:
    return FACTORIES[name](n)


def strongly_connected(support: torch.Tensor) -> bool:
    """Independent oracle: (I + A)^(N-1) has no zero entry iff the digraph is strongly
    connected (every node reaches every other within N-1 hops)."""
    n = support.shape[0]
    reach = torch.eye(n, dtype=torch.float64) + support.double()
    return bool((torch.linalg.matrix_power(reach, max(n - 1, 1)) > 0).all())


def union_support(schedule: MixingSchedule, start: int, length: int) -> torch.Tensor:
    return torch.stack([schedule(k) > 0 for k in range(start, start + length)]).any(dim=0)


# --- the provided schedules satisfy the assumptions --------------------------------


@pytest.mark.parametrize(("name", "n"), ALL)
def test_provided_schedules_pass_inner_check(name, n):
    schedule = make(name, n)
    eps = check_inner_schedule(schedule, horizon=30)
    assert 0.0 < eps <= 1.0
    for k in range(2 * schedule.period + 3):
        w = schedule(k)
        assert w.shape == (n, n) and w.dtype == torch.float64
        assert w.diagonal().min() >= eps and w[w > 0].min() >= eps
    # The returned ε is the one the check then accepts as a requirement.
    assert check_inner_schedule(schedule, horizon=30, epsilon=eps) == eps


@pytest.mark.parametrize(("name", "n"), ALL)
def test_outer_check_accepts_only_complete_graphs(name, n):
    schedule = make(name, n)
    # A cycle on <= 2 learners and a ring on <= 3 are complete graphs too; time-varying
    # steps include W = I.
    small = {"ring": 3, "ring_heavy_self": 3, "directed_cycle": 2}.get(name, 1)
    complete = name == "complete" or n <= small
    if complete:
        assert 0.0 < check_outer_schedule(schedule, horizon=5) <= 1.0
    else:
        with pytest.raises(GraphAssumptionError, match="Assumption 3 \\(outer graph complete\\)"):
            check_outer_schedule(schedule, horizon=20)


def test_complete_schedule_values():
    assert torch.equal(CompleteSchedule(n_learners=4)(7), torch.full((4, 4), 0.25,
                                                                     dtype=torch.float64))
    assert check_outer_schedule(CompleteSchedule(n_learners=5)) == pytest.approx(0.2)


def test_ring_and_cycle_structure():
    ring = RingSchedule(n_learners=5, self_weight=0.2)
    w = ring(0)
    assert torch.equal(w, w.T)
    assert ring.neighbors(0, 0) == [1, 4]
    assert w[0, 1] == pytest.approx(0.4) and w[0, 0] == pytest.approx(0.2)
    assert RingSchedule(n_learners=2, self_weight=0.25)(0).tolist() == [[0.25, 0.75],
                                                                         [0.75, 0.25]]
    assert RingSchedule(n_learners=1)(0).tolist() == [[1.0]]
    cycle = DirectedCycleSchedule(n_learners=4)
    assert cycle.edges(0) == [(0, 3), (1, 0), (2, 1), (3, 2)]  # v receives from v - 1
    assert cycle.neighbors(2, 0) == [1]
    assert not torch.equal(cycle(0), cycle(0).T)


# --- the time-varying family -------------------------------------------------------


@pytest.mark.parametrize("n", [3, 4, 7, 10])
@pytest.mark.parametrize("period", [2, 3, 5, 12])
def test_time_varying_needs_the_whole_window(n, period):
    schedule = TimeVaryingSchedule(n_learners=n, period=period, seed=n + period)
    assert schedule.period == period
    for k in range(3 * period):
        # No single step is strongly connected, so the window check is meaningful ...
        assert not strongly_connected(schedule(k) > 0)
        # ... but every window of `period` steps is.
        assert strongly_connected(union_support(schedule, k, period))
    # B is tight: some window of B - 1 steps misses a segment.
    assert not all(strongly_connected(union_support(schedule, k, period - 1))
                   for k in range(period))
    check_inner_schedule(schedule, horizon=3 * period)
    with pytest.raises(GraphAssumptionError, match="Assumption 1"):
        check_inner_schedule(MatrixSchedule([schedule(k) for k in range(period)],
                                            period=period - 1))


def test_time_varying_is_directed_and_a_permutation_mix():
    schedule = TimeVaryingSchedule(n_learners=7, period=2, seed=0)
    w = schedule(0)
    assert not torch.equal(w, w.T)  # segments of >= 3 learners are directed cycles
    off = w - 0.5 * torch.eye(7, dtype=torch.float64)
    # W = s I + (1 - s) P: the rest is a scaled permutation matrix.
    assert torch.equal((off * 2).sum(0), torch.ones(7, dtype=torch.float64))
    assert set(torch.unique(off * 2).tolist()) == {0.0, 1.0}


def test_time_varying_validation():
    with pytest.raises(ValueError, match="period=1"):
        TimeVaryingSchedule(n_learners=3, period=1)
    TimeVaryingSchedule(n_learners=2, period=1)  # a swap every step is fine for N = 2
    with pytest.raises(ValueError, match="self_weight"):
        TimeVaryingSchedule(n_learners=3, self_weight=1.0)
    with pytest.raises(ValueError, match="seed"):
        TimeVaryingSchedule(n_learners=3, seed=-1)
    with pytest.raises(ValueError, match="n_learners"):
        RingSchedule(n_learners=0)
    with pytest.raises(ValueError, match="self_weight"):
        DirectedCycleSchedule(n_learners=3, self_weight=0.0)
    with pytest.raises(ValueError, match="k must be"):
        RingSchedule(n_learners=3)(-1)
    with pytest.raises(ValueError, match="learner index"):
        RingSchedule(n_learners=3).neighbors(3, 0)


# --- invalid schedules are rejected with the assumption named ----------------------


@pytest.mark.parametrize("matrices", [
    [np.eye(3)],  # nobody ever talks
    [np.kron(np.eye(2), np.full((2, 2), 0.5))],  # two disconnected blocks {0,1}, {2,3}
    # directed: 0 → 1 → 2 as a path can never bring information back to 0
    [np.array([[1.0, 0, 0], [0, 0.5, 0.5], [0, 0.5, 0.5]]), np.eye(3)],
])
def test_disconnected_schedule_fails_assumption_1(matrices):
    with pytest.raises(GraphAssumptionError, match="Assumption 1 \\(B-strong connectivity"):
        check_inner_schedule(MatrixSchedule(matrices))


def test_window_longer_than_claimed_period_fails_then_passes():
    swap01 = np.array([[0.5, 0.5, 0], [0.5, 0.5, 0], [0, 0, 1.0]])
    swap12 = np.array([[1.0, 0, 0], [0, 0.5, 0.5], [0, 0.5, 0.5]])
    with pytest.raises(GraphAssumptionError, match="k=0..0"):
        check_inner_schedule(MatrixSchedule([swap01, swap12], period=1))
    assert check_inner_schedule(MatrixSchedule([swap01, swap12])) == 0.5


def test_row_stochastic_only_fails_assumption_2i():
    w = np.array([[0.5, 0.5, 0.0], [0.5, 0.5, 0.0], [0.4, 0.3, 0.3]])  # rows sum to 1
    with pytest.raises(GraphAssumptionError, match="Assumption 2\\(i\\) \\(doubly stochastic\\)"
                       ".*columns \\[0, 1, 2\\]"):
        check_inner_schedule(MatrixSchedule([np.eye(3), w]))


def test_negative_entry_fails_assumption_2i():
    w = np.array([[1.2, -0.2], [-0.2, 1.2]])  # doubly stochastic sums, negative weight
    with pytest.raises(GraphAssumptionError, match="Assumption 2\\(i\\).*negative"):
        check_inner_schedule(MatrixSchedule([w]))
    with pytest.raises(GraphAssumptionError, match="Assumption 2\\(i\\).*Assumption 3"):
        check_outer_schedule(MatrixSchedule([w]))


def test_zero_diagonal_fails_assumption_2ii():
    swap = np.array([[0.0, 1.0], [1.0, 0.0]])
    with pytest.raises(GraphAssumptionError, match="Assumption 2\\(ii\\) \\(non-degenerate, ε = "
                       ".*k=0.*learners \\[0, 1\\]"):
        check_inner_schedule(MatrixSchedule([swap]))
    cycle = DirectedCycleSchedule(n_learners=3)(0).numpy()
    with pytest.raises(GraphAssumptionError, match="Assumption 2\\(ii\\).*k=1"):
        check_inner_schedule(MatrixSchedule([cycle, np.roll(np.eye(3), 1, axis=1)]))


def test_epsilon_requirement():
    ring = RingSchedule(n_learners=5, self_weight=0.6)  # neighbours get 0.2
    assert check_inner_schedule(ring) == pytest.approx(0.2)
    assert check_inner_schedule(ring, epsilon=0.2) == 0.2  # within atol of 0.2
    with pytest.raises(GraphAssumptionError, match="ε = 0.3\\).*positive weights"):
        check_inner_schedule(ring, epsilon=0.3)
    with pytest.raises(GraphAssumptionError, match="ε = 0.7\\).*self-weights"):
        check_inner_schedule(ring, epsilon=0.7)
    with pytest.raises(ValueError, match="epsilon"):
        check_inner_schedule(ring, epsilon=0.0)


@pytest.mark.parametrize(("matrices", "match"), [
    ([np.full((3, 4), 0.25)], "k=0 has shape \\(3, 4\\), expected \\[3, 3\\]"),
    ([np.full((2, 2), 0.5), np.full((3, 3), 1 / 3)], "k=1 has shape \\(3, 3\\)"),
    ([np.full((2, 2), 0.5), np.full((2, 2), np.nan)], "k=1 has non-finite"),
])
def test_bad_shape_or_values(matrices, match):
    with pytest.raises(ValueError, match=match):
        check_inner_schedule(MatrixSchedule(matrices))
    with pytest.raises(ValueError, match=match.replace("k=", "n=")):
        check_outer_schedule(MatrixSchedule(matrices))


def test_matrix_schedule_basics():
    with pytest.raises(ValueError, match="non-empty"):
        MatrixSchedule([])
    with pytest.raises(ValueError, match="2-D"):
        MatrixSchedule([np.ones(3)])
    s = MatrixSchedule([np.eye(2), [[0.5, 0.5], [0.5, 0.5]]])
    assert s.period == 2 and s.n_learners == 2
    assert s.edges(0) == [] and s.edges(3) == [(0, 1), (1, 0)]
    assert check_outer_schedule(MatrixSchedule([[[0.5, 0.5], [0.5, 0.5]]])) == 0.5


# --- mixing semantics: average preserved, consensus reached ------------------------


@pytest.mark.parametrize(("name", "n"), [(name, n) for name, n in ALL if n >= 2])
def test_mixing_preserves_average_and_reaches_consensus(name, n):
    schedule = make(name, n)
    gen = torch.Generator().manual_seed(n)
    x = torch.randn(n, 3, generator=gen, dtype=torch.float64)  # one row per learner
    mean0 = x.mean(0)
    for k in range(1500):
        x = schedule(k) @ x
        if k < 5:
            torch.testing.assert_close(x.mean(0), mean0, rtol=0, atol=1e-12)
    torch.testing.assert_close(x.mean(0), mean0, rtol=0, atol=1e-10)
    assert (x - x.mean(0)).abs().max() < 1e-8


# --- determinism --------------------------------------------------------------------


@pytest.mark.parametrize("name", list(FACTORIES))
def test_same_args_same_sequence(name):
    a, b = make(name, 7), make(name, 7)
    torch.manual_seed(0)
    np.random.seed(0)  # noqa: NPY002 - global RNG state must not matter
    seq_a = [a(k) for k in range(25)]
    torch.manual_seed(1)
    np.random.seed(1)  # noqa: NPY002
    seq_b = [b(k) for k in reversed(range(25))][::-1]
    assert all(torch.equal(u, v) for u, v in zip(seq_a, seq_b, strict=True))


def test_seed_changes_time_varying_order_only():
    a = TimeVaryingSchedule(n_learners=6, period=2, seed=0)
    b = TimeVaryingSchedule(n_learners=6, period=2, seed=5)
    assert not all(torch.equal(a(k), b(k)) for k in range(2))
    check_inner_schedule(b)


def test_returned_matrix_is_a_copy():
    s = RingSchedule(n_learners=3)
    s(0)[0, 0] = 99.0
    assert s(0)[0, 0] == pytest.approx(1 / 3)
