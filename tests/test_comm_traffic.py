"""What learners send: the traffic counters against a count by hand, compressed messages
(encoding, error feedback, the fixed point they reach), dropped redundant rounds, and
the trainer's numbers with each option (bit for bit where the option is lossless).

The torch.distributed side (same numbers and same counts as here) is in
tests/test_comm_distributed.py.
"""

from __future__ import annotations

import numpy as np
import pytest
import tiny_dicrl
import torch

from dicrl_torch.checks import InvalidSetting
from dicrl_torch.comm import (
    CompleteSchedule,
    DirectedCycleSchedule,
    LinkFailures,
    RingSchedule,
    SimulatedCommunicator,
    TimeVaryingSchedule,
)
from dicrl_torch.comm.communicator import LENGTH_BYTES, fixed_order_mix
from dicrl_torch.comm.compression import Compression
from dicrl_torch.comm.traffic import PHASES, Traffic

SPLIT = tiny_dicrl.SPLIT
N = len(SPLIT)


@pytest.fixture(scope="module")
def tiny():
    return tiny_dicrl.build_tiny()


def trained(tiny, iterations=4, **comm_kw):
    comm = SimulatedCommunicator(N, **comm_kw)
    t = tiny_dicrl.make_trainer(tiny, communicator=comm)
    t.train(iterations)
    return t


# ---------------------------------------------------------------------- the codec
def test_lossless_messages_carry_exactly_the_changed_entries():
    g = torch.Generator().manual_seed(0)
    copy = torch.randn(40, generator=g, dtype=torch.float64)
    x = copy.clone()
    x[[3, 17]] = torch.tensor([1e-300, -7.25e12], dtype=torch.float64)
    c = Compression()
    msg = c.encode(x, copy)
    new, n = Compression.apply(msg, copy)
    assert torch.equal(new, x) and n == 2
    # header, two uint16 indices (cheaper than a 5-byte mask), two float64 values
    assert len(msg) == 1 + 2 * 2 + 2 * 8
    assert c.encode(x, x) == b""  # nothing changed: nothing to send
    dense = torch.randn(40, generator=g, dtype=torch.float64)
    assert len(c.encode(dense, copy)) == 1 + 40 * 8  # every entry: no index at all
    half = dense.clone()
    half[::2] = copy[::2]
    assert len(c.encode(half, copy)) == 1 + 5 + 20 * 8  # a bitmask beats 20 indices


@pytest.mark.parametrize("bits", [8, 16])
def test_quantised_messages_err_by_at_most_half_a_step(bits):
    g = torch.Generator().manual_seed(bits)
    copy = torch.randn(300, generator=g, dtype=torch.float64)
    x = copy + torch.randn(300, generator=g, dtype=torch.float64) * 3
    msg = Compression(bits=bits).encode(x, copy)
    new, n = Compression.apply(msg, copy)
    level = 2 ** (bits - 1) - 1
    step = (x - copy).abs().max().item() / level
    assert (new - x).abs().max().item() <= 0.5 * step * (1 + 1e-6)
    assert len(msg) <= 1 + 38 + 2 + 300 * bits // 8  # header, mask, scale, values
    assert 0 < n <= 300


@pytest.mark.parametrize("x", [1e-30, 3.0e-8, 0.1, 1.0, 1.00390625, 7.77e5, 3.3e38])
def test_the_scale_is_the_smallest_bfloat16_not_below_the_largest_difference(x):
    from dicrl_torch.comm.compression import _bfloat16_at_least, _from_bfloat16

    scale = _from_bfloat16(_bfloat16_at_least(x))
    assert scale >= x and scale <= x * (1 + 2 ** -7)  # 8 significant bits
    bits = np.array([scale], dtype=np.float32).view(np.uint32)[0]
    assert bits & 0xFFFF == 0


def test_entries_within_the_threshold_are_not_sent():
    copy = torch.zeros(10, dtype=torch.float64)
    x = torch.tensor([0.0, 1e-5, -2e-3, 0.5, 0, 0, 0, 0, 0, 1e-4], dtype=torch.float64)
    for bits in (64, 8):
        new, n = Compression(threshold=1e-3, bits=bits).apply(
            Compression(threshold=1e-3, bits=bits).encode(x, copy), copy)
        assert n == 2 and new[1] == 0 and new[9] == 0 and new[3] != 0 and new[2] != 0


def test_settings_and_garbage_are_refused():
    with pytest.raises(InvalidSetting, match="bits"):
        Compression(bits=12)
    with pytest.raises(InvalidSetting, match="threshold"):
        Compression(threshold=-1.0)
    msg = Compression().encode(torch.arange(5.0, dtype=torch.float64),
                               torch.zeros(5, dtype=torch.float64))
    msg = bytes([2 << 4 | msg[0] & 0xF]) + b"\x00\x01\x02"  # an index list of no length
    with pytest.raises(ValueError, match="disagree on its shape"):
        Compression.apply(msg, torch.zeros(5, dtype=torch.float64))


# ---------------------------------------------------------------------- mixing
def random_rows(seed, n=N, s=6):
    return torch.randn(n, s, generator=torch.Generator().manual_seed(seed),
                       dtype=torch.float64) * 10


@pytest.mark.parametrize("W", [CompleteSchedule(n_learners=N)(0), RingSchedule(n_learners=N)(0),
                               torch.rand(N, N, generator=torch.Generator().manual_seed(1),
                                          dtype=torch.float64)])
def test_lossless_mixing_equals_todays_mixing_bit_for_bit(W):
    plain, lossless = SimulatedCommunicator(N), SimulatedCommunicator(N, compression=Compression())
    for step in range(4):  # the copies persist: later rounds send differences
        x = random_rows(step)
        x[:, :3] = 1.0  # unchanged entries after the first round
        for keep in (True, False):
            assert torch.equal(lossless.mix(x, W, "eta", keep_residual=keep),
                               plain.mix(x, W, "eta"))


def test_compressed_gossip_reaches_the_exact_average():
    """Error feedback: repeated int8 mixing on a ring converges to the average of the
    start values (the uncompressed fixed point), because keeping each learner's residual
    preserves the sum exactly and the differences, hence the errors, shrink to 0."""
    W = RingSchedule(n_learners=5)(0)
    x = random_rows(7, n=5, s=9)
    target = x.mean(0)
    comm = SimulatedCommunicator(5, compression=Compression(bits=8))
    for _ in range(300):
        x = comm.mix(x, W, "tracker")
        assert torch.allclose(x.sum(0), 5 * target, rtol=0, atol=1e-10)
    assert (x - target).abs().max().item() < 1e-10
    # without feedback (each round quantised afresh against 0) it stalls at the quantum
    stale = random_rows(7, n=5, s=9)
    for _ in range(300):
        q = torch.stack([Compression.apply(Compression(bits=8).encode(r, torch.zeros(9)),
                                           torch.zeros(9, dtype=torch.float64))[0]
                         for r in stale])
        stale = fixed_order_mix(q, W, list(range(5)))
    assert (stale - target).abs().max().item() > 1e-4


# ---------------------------------------------------------------------- counting
def test_counts_match_a_count_by_hand(tiny):
    """Today's exchange: every round is a float64 all-gather to the N - 1 others."""
    t = trained(tiny, iterations=3)
    d, p = t.learner_model.cost_dim, t.learner_model.reward_dim + 1
    K = t.K
    for v in range(N):
        inner = outer = 0
        for n, h in enumerate(t.history):
            inner += h["inner_processes"] * (K - 1) * p  # η mixes
            outer += d + d + (d if n > 0 else 0)  # gather, ω_c mix, tracker mix (n >= 1)
        rep = t.comm.traffic.report(v)
        for phase, scalars in (("inner", inner), ("outer", outer)):
            size = p if phase == "inner" else d  # scalars per message
            assert rep["sent"][phase] == {"messages": (N - 1) * scalars // size,
                                          "scalars": (N - 1) * scalars,
                                          "bytes": (N - 1) * 8 * scalars}
            assert rep["received"][phase] == rep["sent"][phase]  # all rows equal-sized
        assert rep["algorithm_bytes_sent"] == (N - 1) * 8 * (inner + outer)
        assert t.history[-1]["bytes_sent"][v] == rep["algorithm_bytes_sent"]
    t.disagreement()
    assert t.comm.traffic.report(0)["sent"]["diagnostics"]["scalars"] == (N - 1) * d


def test_compressed_counts_are_the_bytes_of_the_messages_sent(tiny):
    t = trained(tiny, iterations=2, compression=Compression(bits=8), record=True)
    kinds = {m.encoding for m in t.comm.messages}
    assert kinds == {"compressed", "float64"}  # float64: the all-gathers of ω_c
    for m in t.comm.messages:
        assert m.recipients == tuple(u for u in range(N) if u != m.sender)
        if m.encoding == "compressed":
            assert m.nbytes == LENGTH_BYTES + len(m.payload) and m.field != "cost_weights" \
                or m.field == "cost_weights"
        else:
            assert m.nbytes == 8 * int(np.prod(m.shape)) and not m.payload
    for v in range(N):
        report = t.comm.traffic.report(v)
        sent = sum(len(m.recipients) * m.nbytes for m in t.comm.messages if m.sender == v)
        assert sent == sum(report["sent"][p]["bytes"] for p in PHASES)
        received = sum(m.nbytes for m in t.comm.messages if m.sender != v)
        assert received == sum(report["received"][p]["bytes"] for p in PHASES)


def test_traffic_survives_a_checkpoint_by_adding():
    a = Traffic([0, 1])
    a.add(1, "sent", "inner", messages=2, scalars=10, nbytes=80)
    b = Traffic([1])
    b.add(1, "sent", "control", messages=1, scalars=0, nbytes=9)
    b.load_state_dict(a.state_dict())
    assert b.report(1)["sent"]["inner"]["bytes"] == 80 and b.bytes_sent(1) == 80
    assert b.report(1)["sent"]["control"]["bytes"] == 9


# ---------------------------------------------------------------------- the trainer
def test_lossless_options_give_todays_run_bit_for_bit_with_fewer_bytes(tiny):
    today = trained(tiny)
    lean = trained(tiny, compression=Compression(), skip_redundant_rounds=True, record=True)
    for key in ("cost_weights", "eta", "eta_bar", "tracker"):
        assert torch.equal(getattr(today.state, key), getattr(lean.state, key)), key
    # distinct initial ω_c: the half steps at n = 0, the LSCA targets once ω_c are equal
    by_iteration = [m.field for m in lean.comm.messages if m.sender == 0
                    and m.field in ("cost_weights", "lsca_target")]
    assert by_iteration == ["cost_weights", "cost_weights"] + ["lsca_target"] * 3
    for v in range(N):
        assert lean.comm.traffic.bytes_sent(v) < today.comm.traffic.bytes_sent(v)


def test_the_redundant_gather_is_skipped_only_where_omega_c_are_known_equal(tiny):
    # distinct initial ω_c: gathered at n = 0, then equal after the complete W̄
    t = trained(tiny, iterations=3, skip_redundant_rounds=True, record=True)
    gathers = [m for m in t.comm.messages if m.field == "cost_weights" and m.sender == 0]
    # one all-gather (n = 0) and one ω_c mix per iteration
    assert len(gathers) == 1 + 3
    plain = trained(tiny, iterations=3)
    assert torch.equal(t.state.eta_bar, plain.state.eta_bar)
    assert [h["inner_processes"] for h in t.history] == [h["inner_processes"]
                                                          for h in plain.history]


def test_int8_messages_keep_the_trackers_sum_and_stay_near_the_exact_run(tiny):
    today = trained(tiny, iterations=6)
    t = trained(tiny, iterations=6, compression=Compression(bits=8),
                skip_redundant_rounds=True)
    st = t.state
    # gradient tracking's invariant: Σ_v y_v = Σ_v LGA_v, kept by the residual
    assert torch.allclose(st.tracker.sum(0), st.last_lga.sum(0), rtol=0, atol=1e-12)
    # mixed without the residual under the uniform W̄, the ω_c are equal bit for bit
    assert bool((st.cost_weights == st.cost_weights[0]).all())
    assert [h["inner_processes"] for h in t.history] == [h["inner_processes"]
                                                          for h in today.history]
    assert (st.cost_weights - today.state.cost_weights).abs().max().item() < 0.01
    assert np.array_equal((st.cost_weights >= 0.5).numpy(),
                          (today.state.cost_weights >= 0.5).numpy())
    for v in range(N):
        # 3 distinct inner processes and a float64 gather of ω_c at n = 0, then int8
        assert today.comm.traffic.bytes_sent(v) >= 4 * t.comm.traffic.bytes_sent(v)


def test_a_compressed_run_resumes_bit_for_bit(tiny):
    whole = trained(tiny, iterations=4, compression=Compression(bits=8))
    first = trained(tiny, iterations=2, compression=Compression(bits=8))
    sd = first.state_dict()
    comm = SimulatedCommunicator(N, compression=Compression(bits=8))
    resumed = tiny_dicrl.make_trainer(tiny, communicator=comm)
    resumed.load_state_dict(sd)
    resumed.train(4)
    for key in ("cost_weights", "eta_bar", "tracker"):
        assert torch.equal(getattr(whole.state, key), getattr(resumed.state, key)), key
    assert whole.comm.traffic.report(1) == resumed.comm.traffic.report(1)
    # a checkpoint of another compression is refused
    other = tiny_dicrl.make_trainer(tiny, communicator=SimulatedCommunicator(N))
    with pytest.raises(ValueError, match="differently configured"):
        other.load_state_dict(sd)


def test_the_audit_of_compressed_messages_replays_to_the_receivers_copies(tiny):
    """The privacy audit holds compressed messages as sent: only allowed fields, and
    decoding the recorded bytes in order rebuilds exactly the copies every receiver
    holds, none of which is a learner's private statistic."""
    from dicrl_torch.comm import ALLOWED_FIELDS

    comm = SimulatedCommunicator(N, compression=Compression(bits=8), record=True,
                                 skip_redundant_rounds=True)
    t = tiny_dicrl.make_trainer(tiny, communicator=comm)
    # the copies start at the public initial η and ω_c (0 for the trackers)
    start = {k: v.clone() for k, v in comm._copies.items()}
    assert set(start) == {"eta", "cost_weights", "lsca_target"}
    assert torch.equal(start["eta"][:, -1], torch.full((N,), -1.0, dtype=torch.float64))
    t.train(3)
    private = [x for st in t.stats for x in (st.mu_r_hat, st.cost_accrual)]
    replayed: dict[tuple[str, int], torch.Tensor] = {}
    for m in t.comm.messages:
        assert m.field in ALLOWED_FIELDS
        if m.encoding != "compressed":
            continue
        key = (m.field, m.sender)
        initial = start[m.field][m.sender] if m.field in start else torch.zeros(
            int(np.prod(m.shape)), dtype=torch.float64)
        copy = replayed.get(key, initial)
        replayed[key], _ = Compression.apply(m.payload, copy)
        for x in private:
            assert not (replayed[key].shape == x.shape and torch.allclose(replayed[key], x))
    for (field, sender), copy in replayed.items():
        assert torch.equal(copy, t.comm._copies[field][sender])


# ---------------------------------------------------------------------- links that fail
@pytest.mark.parametrize("schedule", [CompleteSchedule(n_learners=5), RingSchedule(n_learners=5),
                                      TimeVaryingSchedule(n_learners=5, period=2),
                                      DirectedCycleSchedule(n_learners=5)])
def test_realised_graphs_are_doubly_stochastic_on_the_links_left(schedule):
    failures = LinkFailures(0.3, seed=4)
    downs = []
    for k in range(40):
        W = schedule(k)
        R = failures.realise(W, 2, 0, k)
        assert torch.equal(R, failures.realise(W, 2, 0, k))  # the same round: the same graph
        assert torch.allclose(R.sum(0), torch.ones(5, dtype=torch.float64), atol=1e-12)
        assert torch.allclose(R.sum(1), torch.ones(5, dtype=torch.float64), atol=1e-12)
        assert (R >= 0).all() and (R.diagonal() > 0).all()
        off = ~torch.eye(5, dtype=torch.bool)
        assert not ((R > 0) & (W == 0) & off).any()  # no link appears
        downs.append(((W > 0) & (R == 0) & off).sum().item() / ((W > 0) & off).sum().item())
    if isinstance(schedule, (CompleteSchedule, RingSchedule)):
        # symmetric: a failed link's weight goes to both ends, the others stay as they were
        assert 0.15 < np.mean(downs) < 0.45
        W, R = schedule(0), failures.realise(schedule(0), 2, 0, 0)
        kept = (R > 0) & ~torch.eye(5, dtype=torch.bool)
        assert torch.equal(R[kept], W[kept])
    assert not torch.equal(failures.realise(schedule(0), 2, 0, 0),
                           failures.realise(schedule(0), 2, 1, 0)) or \
        not torch.equal(failures.realise(schedule(0), 2, 0, 0),
                        failures.realise(schedule(0), 3, 0, 0))


def test_a_directed_cycle_with_a_link_down_cannot_mix():
    """A doubly stochastic matrix is a mix of permutations: with one link of a directed
    cycle down no cycle is left through the others, so only the identity remains."""
    W = DirectedCycleSchedule(n_learners=4)(0)
    failures = LinkFailures(0.5, seed=0)
    for k in range(20):
        R = failures.realise(W, 0, 0, k)
        if torch.equal(R > 0, W > 0):
            assert torch.equal(R, W)
        else:
            assert torch.allclose(R, torch.eye(4, dtype=torch.float64), atol=1e-12)


def test_training_over_failing_links(tiny):
    exact = trained(tiny, iterations=4)
    lossy = trained(tiny, iterations=4, link_failure=0.2, link_seed=1)
    again = trained(tiny, iterations=4, link_failure=0.2, link_seed=1)
    other = trained(tiny, iterations=4, link_failure=0.2, link_seed=2)
    st = lossy.state
    assert torch.equal(st.eta_bar, again.state.eta_bar)  # seeded: the same run
    assert not torch.equal(st.eta_bar, other.state.eta_bar)
    assert not torch.equal(st.eta_bar, exact.state.eta_bar)
    assert torch.allclose(st.tracker.sum(0), st.last_lga.sum(0), rtol=0, atol=1e-12)
    assert all("disconnected_inner_processes" in h for h in lossy.history)
    assert "disconnected_inner_processes" not in exact.history[0]
    assert np.array_equal((st.cost_weights >= 0.5).numpy(),
                          (exact.state.cost_weights >= 0.5).numpy())


def test_failing_links_are_refused_with_compressed_messages():
    with pytest.raises(InvalidSetting, match="link_failure"):
        SimulatedCommunicator(N, compression=Compression(), link_failure=0.2)
    with pytest.raises(InvalidSetting, match="link_failure"):
        SimulatedCommunicator(N, link_failure=1.0)


def test_inner_fields_take_their_own_bits():
    c = Compression(bits=8, inner_bits=16)
    assert c.for_field("eta").bits == 16 and c.for_field("inner_tracker").bits == 16
    assert c.for_field("tracker") is c and c.for_field("lsca_target") is c
    assert not c.lossless and Compression(inner_bits=64).lossless
    with pytest.raises(InvalidSetting, match="inner_bits"):
        Compression(inner_bits=4)
    # the multiplier's step is 100 times the reward weights': in 8 bits their quantum is
    # as large as they are, in 16 bits a 500th of them
    copy = torch.zeros(3, dtype=torch.float64)
    x = torch.tensor([0.013, -0.021, -3.0], dtype=torch.float64)
    for bits, worst in ((8, 0.5), (16, 0.005)):
        got, _ = Compression.apply(Compression(bits=bits).encode(x, copy), copy)
        relative = ((got - x).abs() / x.abs())[:2].max().item()
        assert (relative > worst / 10) if bits == 8 else (relative < worst), (bits, relative)


def test_checkpoints_move_between_exchanges_that_give_the_same_numbers(tiny):
    """The paper's exchange and lossless messages give the same numbers, so a checkpoint
    of one continues under the other (a committed checkpoint from before the options
    too), bit for bit; a lossy setting is refused."""
    whole = trained(tiny, iterations=4)
    first = trained(tiny, iterations=2, compression=Compression(), skip_redundant_rounds=True)
    resumed = tiny_dicrl.make_trainer(tiny, communicator=SimulatedCommunicator(N))
    resumed.load_state_dict(first.state_dict())
    resumed.train(4)
    assert torch.equal(whole.state.cost_weights, resumed.state.cost_weights)
    assert torch.equal(whole.state.eta_bar, resumed.state.eta_bar)
    lossy = tiny_dicrl.make_trainer(tiny, communicator=SimulatedCommunicator(
        N, compression=Compression(bits=8)))
    with pytest.raises(ValueError, match="differently configured"):
        lossy.load_state_dict(first.state_dict())
