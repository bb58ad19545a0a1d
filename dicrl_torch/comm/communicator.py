"""Communicators: how learners exchange parameter vectors (docs/design.md §5).

A communicator serves the learners that live in this process (``local_ids``); the
trainer keeps their state stacked along a leading axis. ``mix`` returns, for each
local learner ``v``, ``Σ_{v'} W[v, v'] x_{v'}``, accumulated in a fixed order
(``v' = 0, 1, ..``) so that every backend performs the same floating-point operations
and produces identical numbers.

Only the fields listed in :data:`ALLOWED_FIELDS` may be sent; every exchange is counted
(:class:`~dicrl_torch.comm.traffic.Traffic`), and with ``record`` every message is
logged (field, shape, sender, recipients, phase, bytes, encoding) so that a test can
audit what left a learner.

:class:`Communicator` holds the mechanism both backends share (counting, compressed
mixing with public copies); a backend supplies only the transport: ``_exchange_dense``
(an all-gather of equal-shaped float64 rows) and ``_exchange_messages`` (one byte string
from each local learner to every other learner).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from dicrl_torch.checks import InvalidSetting, setting_bool
from dicrl_torch.comm.compression import Compression
from dicrl_torch.comm.graphs import LinkFailures
from dicrl_torch.comm.traffic import Traffic, phase_of

# What may leave a learner: η = [ω_r, λ], ω_c and the gradient trackers (Algorithm 1's,
# and the optional gradient-tracking inner variant's), and, where every learner's ω_c is
# known to be equal, the LSCA target ω̃ in place of ω_c's half step: every receiver knows
# ω_c and β(n), so ω̃ = ω_c + (half - ω_c) / β reveals what the half step does; and once
# per run, for the grid's certificate, which cost features a learner's shard accrues (a
# bitmask: with budget 0 these are the features ω_c's LSCA target already pins to 0).
ALLOWED_FIELDS = ("eta", "cost_weights", "tracker", "inner_tracker", "lsca_target",
                  "demonstrated")
# Control values a run coordinates its learner processes with (never learner data): the
# run directory and id, and which outer iterations each learner has checkpointed.
CONTROL_FIELDS = ("run_directory", "checkpointed_iterations")
# Bytes of the length that precedes a compressed message on the wire.
LENGTH_BYTES = 4


def check_control(field: str, value) -> bytes:
    """``value`` as the JSON bytes :meth:`gather_control` sends; a field not in
    :data:`CONTROL_FIELDS` or a value JSON cannot hold is refused."""
    import json

    if field not in CONTROL_FIELDS:
        raise ValueError(f"Control field {field!r} is not one a run exchanges; allowed: "
                         f"{CONTROL_FIELDS}.")
    return json.dumps(value).encode()


@dataclass
class MessageRecord:
    """One message of the audit log: what ``sender`` sent to ``recipients``.

    ``encoding`` is "float64" (the values themselves), "json" (a control value) or
    "compressed" (``payload`` holds the bytes as sent, which
    :meth:`Compression.apply <dicrl_torch.comm.compression.Compression.apply>` decodes).
    """

    field: str
    shape: tuple[int, ...]
    sender: int
    recipients: tuple[int, ...] = ()
    phase: str = ""
    nbytes: int = 0
    encoding: str = "float64"
    payload: bytes = b""


class Communicator:
    """What both backends share. Subclasses set ``n_learners`` and ``local_ids`` and
    call :meth:`_setup`.

    Options (the ``comm`` config group):
        compression: :class:`~dicrl_torch.comm.compression.Compression` of the mixed
            fields (η, ω_c, the trackers), or None: float64 all-gathers, as the paper.
        skip_redundant_rounds: the trainer does not gather ω_c when every learner's is
            known to be equal (the initial ω_c, or after a W̄(n) whose rows are equal).
        diagnostics: the run gathers the consensus distances for TensorBoard and
            results.json (reported apart from the algorithm's traffic).
        link_failure: the probability that a link of the inner graph W(k) fails in a
            round (:class:`~dicrl_torch.comm.graphs.LinkFailures`; the outer rounds stay
            reliable, as Assumption 3 needs); 0: none.
        link_seed: the seed of the failures (the run's seed).
    """

    n_learners: int

    @staticmethod
    def check_settings(**settings) -> None:
        """Refuse the options given as the constructor would (``compression`` as a
        :class:`Compression` or the mapping of its arguments); others are ignored. A config
        checks them before any process starts.

        Raises:
            InvalidSetting: naming the option, what it must be and an example.
        """
        compression = settings.get("compression")
        if isinstance(compression, dict):
            try:
                compression = Compression(**{k: v for k, v in compression.items()
                                             if k != "_target_"})
            except InvalidSetting as e:  # named as the comm node's key says
                raise e.renamed({e.name: f"compression.{e.name}"}) from None
        for name in ("record", "skip_redundant_rounds", "diagnostics"):
            if name in settings:
                setting_bool(name, settings[name], example=True)
        failure = settings.get("link_failure", 0.0)
        if failure:  # the seed matters only to failures (the run's seed is checked apart)
            LinkFailures(failure, settings.get("link_seed", 0))
        if failure and compression is not None:
            raise InvalidSetting("link_failure", failure, "0 while messages are compressed, "
                                 "or set comm.compression=null: compressed messages update "
                                 "copies that every receiver must hold, and a lost message "
                                 "would leave a receiver's copy behind", 0.0)

    def _setup(self, *, record: bool, compression: Compression | None,
               skip_redundant_rounds: bool, diagnostics: bool, link_failure: float = 0.0,
               link_seed: int = 0) -> None:
        if compression is not None and not isinstance(compression, Compression):
            raise TypeError(f"compression must be a Compression or None, got "
                            f"{type(compression).__name__}.")
        Communicator.check_settings(
            compression=compression, record=record, diagnostics=diagnostics,
            skip_redundant_rounds=skip_redundant_rounds, link_failure=link_failure,
            link_seed=link_seed)
        self.link_failures = LinkFailures(link_failure, link_seed) if link_failure else None
        self.record, self.compression = record, compression
        self.skip_redundant_rounds, self.diagnostics = skip_redundant_rounds, diagnostics
        self.messages: list[MessageRecord] = []
        self.traffic = Traffic(self.local_ids)
        self._copies: dict[str, torch.Tensor] = {}  # field -> [N_L, s] public copies

    @property
    def local_ids(self) -> list[int]:
        raise NotImplementedError

    def describe(self) -> str:
        """The options that change the numbers (for a checkpoint's fingerprint); "" for
        the paper's numbers (lossless compression too: a checkpoint of either, or from
        before the options, continues under the other)."""
        c, f = self.compression, self.link_failures
        c = None if c is not None and c.lossless else c
        inner = "" if c is None or c.inner_bits is None else f",{c.inner_bits}"
        return " ".join(([] if c is None else [f"compression=({c.threshold:g},{c.bits}{inner})"])
                        + ([] if f is None else [f"link_failure=({f.p:g},{f.seed})"]))

    # ------------------------------------------------------------------ transport
    def _exchange_dense(self, values: torch.Tensor, what: str) -> torch.Tensor:
        """``[n_local, s]`` float64 -> ``[N_L, s]``: every learner's row."""
        raise NotImplementedError

    def _exchange_messages(self, messages: list[bytes], what: str) -> list[bytes]:
        """One message per local learner -> every learner's message, in learner order."""
        raise NotImplementedError

    # ------------------------------------------------------------------ exchanges
    def _check(self, values: torch.Tensor, field: str) -> None:
        if field not in ALLOWED_FIELDS:
            raise ValueError(f"Field {field!r} may not leave a learner; allowed: "
                             f"{ALLOWED_FIELDS}.")
        n = len(self.local_ids)
        if values.dim() < 1 or values.shape[0] != n:
            raise ValueError(f"Expected values [{n}, ...] for the local learners "
                             f"{self.local_ids}, got shape {tuple(values.shape)}.")
        if not values.is_floating_point():
            raise ValueError(f"Only real floating-point values are exchanged, got "
                             f"{values.dtype} for {field!r}.")

    def _count(self, field: str, phase: str, shape: tuple[int, ...], scalars: list[int],
               nbytes: list[int], encoding: str, payloads: list[bytes] | None = None
               ) -> None:
        """Count (and record) that every learner ``u`` sent ``scalars[u]`` scalars in
        ``nbytes[u]`` bytes to each other learner."""
        others = self.n_learners - 1
        for v in self.local_ids:
            self.traffic.add(v, "sent", phase, messages=others, scalars=others * scalars[v],
                             nbytes=others * nbytes[v])
            self.traffic.add(v, "received", phase, messages=others,
                             scalars=sum(scalars) - scalars[v], nbytes=sum(nbytes) - nbytes[v])
            if self.record:
                self.messages.append(MessageRecord(
                    field, shape, v, tuple(u for u in range(self.n_learners) if u != v),
                    phase, nbytes[v], encoding, b"" if payloads is None else payloads[v]))

    def all_gather(self, values: torch.Tensor, field: str, phase: str | None = None
                   ) -> torch.Tensor:
        """``values`` ``[n_local, ...]`` of the local learners -> ``[N_L, ...]``, sent as
        float64 (float16/32/64 round-trip exactly, so numbers are unchanged).

        Args:
            phase: what the exchange is counted under (default: the field's round;
                "diagnostics" for the consensus distances).

        Raises:
            ValueError: the field may not leave a learner, or the shape is wrong.
        """
        self._check(values, field)
        phase = phase_of(field, phase)
        shape = tuple(values.shape[1:])
        flat = values.detach().to(torch.float64).reshape(values.shape[0], -1)
        gathered = self._exchange_dense(flat, f"{field!r}")
        s = flat.shape[1]
        self._count(field, phase, shape, [s] * self.n_learners, [8 * s] * self.n_learners,
                    "float64")
        return gathered.reshape(self.n_learners, *shape).to(values.dtype)

    def mix(self, values: torch.Tensor, W: torch.Tensor, field: str, *,
            keep_residual: bool = True) -> torch.Tensor:
        """Consensus step ``[n_local, ...]`` -> ``[n_local, ...]`` with ``W`` ``[N_L, N_L]``.

        With compression, every learner mixes the public copies ``x̂`` (equal
        everywhere) and, with ``keep_residual``, adds back its own ``x - x̂``: the sum
        over learners is then kept, as gradient tracking needs (CHOCO-gossip with step
        1). Without it the outputs are equal wherever the rows of ``W`` are (ω_c under a
        uniform W̄: one inner process serves every learner). Lossless compression gives
        the uncompressed numbers bit for bit either way.
        """
        if tuple(W.shape) != (self.n_learners, self.n_learners):
            raise ValueError(f"W must be [{self.n_learners}, {self.n_learners}], got "
                             f"{tuple(W.shape)}.")
        if self.compression is None:
            return fixed_order_mix(self.all_gather(values, field), W, self.local_ids)
        copies = self.exchange(values, field).reshape(self.n_learners, -1)
        mixed = fixed_order_mix(copies, W, self.local_ids)
        if keep_residual and not self.compression.for_field(field).lossless:
            x = values.detach().to(torch.float64).reshape(values.shape[0], -1)
            mixed = mixed + (x - copies[self.local_ids])
        return mixed.reshape(values.shape).to(values.dtype)

    def exchange(self, values: torch.Tensor, field: str) -> torch.Tensor:
        """Every learner's public copy of ``field`` ``[N_L, ...]`` (float64) after this
        round, in which the local learners send ``values`` ``[n_local, ...]``: compressed
        against the copies (equal to ``values`` where the compression is lossless), or
        whole (:meth:`all_gather`) without compression."""
        if self.compression is None:
            return self.all_gather(values, field).to(torch.float64)
        self._check(values, field)
        x = values.detach().to(torch.float64).reshape(values.shape[0], -1)  # [n, s]
        copies = self._copies.get(field)
        if copies is None or copies.shape[1] != x.shape[1]:
            copies = torch.zeros(self.n_learners, x.shape[1], dtype=torch.float64)
        codec = self.compression.for_field(field)
        mine = [codec.encode(x[i], copies[v]) for i, v in enumerate(self.local_ids)]
        messages = self._exchange_messages(mine, f"{field!r}")
        decoded = [Compression.apply(m, copies[u]) for u, m in enumerate(messages)]
        copies = torch.stack([c for c, _ in decoded])
        self._copies[field] = copies
        self._count(field, phase_of(field, None), tuple(values.shape[1:]),
                    [n for _, n in decoded], [LENGTH_BYTES + len(m) for m in messages],
                    "compressed", messages)
        return copies.reshape(self.n_learners, *values.shape[1:])

    def seed_copies(self, field: str, values: torch.Tensor) -> None:
        """Start ``field``'s public copies ``[N_L, ...]`` at values every learner knows
        (the initial η and ω_c) instead of 0: an entry that stays where it started is
        then never sent, and stays exact under lossy compression (an ω_c left at 0.5,
        the threshold, is not jittered across it). Copies restored from a checkpoint are
        kept."""
        if field not in self._copies:
            self._copies[field] = values.detach().to(torch.float64).reshape(
                self.n_learners, -1).clone()

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict:
        """The counters and the public copies (a resumed compressed run continues bit
        for bit)."""
        return {"traffic": self.traffic.state_dict(),
                "copies": {k: v.clone() for k, v in self._copies.items()}}

    def load_state_dict(self, sd: dict) -> None:
        self.traffic.load_state_dict(sd["traffic"])
        self._copies = {k: v.clone() for k, v in sd["copies"].items()}


class SimulatedCommunicator(Communicator):
    """All ``n_learners`` learners in one process (``local_ids = 0..N_L-1``).

    Args:
        n_learners: number of learners ``N_L``.
        record: keep a log of every message (for the privacy audit).
        compression, skip_redundant_rounds, diagnostics, link_failure, link_seed: see
            :class:`Communicator`.
    """

    def __init__(self, n_learners: int, record: bool = False, *,
                 compression: Compression | None = None, skip_redundant_rounds: bool = False,
                 diagnostics: bool = True, link_failure: float = 0.0,
                 link_seed: int = 0) -> None:
        if not isinstance(n_learners, int) or isinstance(n_learners, bool) or n_learners < 1:
            raise ValueError(f"n_learners must be a positive int, got {n_learners!r}.")
        self.n_learners = n_learners
        self._setup(record=record, compression=compression,
                    skip_redundant_rounds=skip_redundant_rounds, diagnostics=diagnostics,
                    link_failure=link_failure, link_seed=link_seed)

    @property
    def local_ids(self) -> list[int]:
        return list(range(self.n_learners))

    def _exchange_dense(self, values: torch.Tensor, what: str) -> torch.Tensor:
        return values

    def _exchange_messages(self, messages: list[bytes], what: str) -> list[bytes]:
        return messages

    def gather_control(self, value, field: str) -> list:
        """Every learner's control ``value`` (JSON-able), in learner order: here all
        learners share one process, hence one value. Counted as the distributed backend
        sends it (a length, then the JSON bytes)."""
        data = check_control(field, value)
        size = 8 + len(data)
        self._count(field, "control", (len(data),), [0] * self.n_learners,
                    [size] * self.n_learners, "json")
        return [value] * self.n_learners

    def close(self) -> None:
        pass


def fixed_order_mix(gathered: torch.Tensor, W: torch.Tensor, rows: list[int]) -> torch.Tensor:
    """``out[i] = Σ_{v'} W[rows[i], v'] gathered[v']``, summed in the order v' = 0, 1, ..

    (A matmul may sum rows in different orders; this keeps backends bit-identical.)"""
    W = W.to(gathered.dtype)
    out = []
    for v in rows:
        acc = W[v, 0] * gathered[0]
        for u in range(1, gathered.shape[0]):
            acc = acc + W[v, u] * gathered[u]
        out.append(acc)
    return torch.stack(out)
