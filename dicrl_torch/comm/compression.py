"""Compressed messages with error feedback (docs/design.md §5.3).

Every learner keeps, per field, a *public copy* ``x̂`` of its vector that every other
learner holds too. A round sends only what the copy lacks, encoded by
:class:`Compression`, and sender and receivers apply the same bytes to the copy, so the
copies stay equal everywhere bit for bit. The part of ``x - x̂`` a message leaves out
stays in the next difference: that is the error feedback, and it keeps ``|x - x̂|``
bounded by one quantum instead of letting it accumulate.

- ``threshold`` δ (event-triggered sends): an entry is sent only when it moved more
  than δ from the copy; δ = 0 sends every entry that changed at all.
- ``bits``: 64 sends the new values as float64 (lossless: δ = 0 gives today's numbers
  bit for bit), 32 as float32; 16 or 8 send the difference ``x - x̂`` uniformly
  quantised against the message's largest difference (its scale a bfloat16 rounded up:
  2 bytes), entries that round to 0 left for later.

An encoded message is ``b"" `` (nothing to send) or: one header byte (index scheme,
value format), the index of the entries sent (none when all are, else the cheaper of
a bitmask and a list of uint16/uint32 indices), the scale (quantised formats), the
values. Decoding reads it with ``numpy.frombuffer``: nothing is unpickled.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from dicrl_torch.checks import InvalidSetting, is_int, setting_number

_ALL, _MASK, _IDX16, _IDX32 = 0, 1, 2, 3
INNER_FIELDS = ("eta", "inner_tracker")
_VALUE_TYPES = {64: np.dtype("<f8"), 32: np.dtype("<f4"), 16: np.dtype("<i2"),
                8: np.dtype("i1")}
_BITS = tuple(_VALUE_TYPES)
_BITS_CODE = {b: i for i, b in enumerate(_BITS)}


@dataclass(frozen=True)
class Compression:
    """How one message of a field is encoded against the receivers' copy.

    Args:
        threshold: δ >= 0; entries with ``|x - x̂| <= δ`` are not sent (δ = 0: those
            unchanged).
        bits: 64 or 32 (the values, as float64 or float32) or 16 or 8 (the quantised
            difference).
        inner_bits: the bits of the inner rounds' fields (η, the inner tracker); None:
            ``bits``. η holds the multiplier beside the reward weights, whose steps can be
            a hundredth of its own: quantised against the largest, they would wait for
            several rounds, so they get more bits (they are few: l_r + 1 per message).
    """

    threshold: float = 0.0
    bits: int = 64
    inner_bits: int | None = None

    def __post_init__(self) -> None:
        setting_number("threshold", self.threshold, low=0, example=1e-4,
                       why="entries that moved less than this from the receivers' copy "
                           "are not sent")
        for name in ("bits", "inner_bits"):
            value = getattr(self, name)
            if name == "inner_bits" and value is None:
                continue
            if not is_int(value) or value not in _BITS:
                raise InvalidSetting(name, value, "one of 64, 32, 16, 8 (64/32: values as "
                                     "float64/float32; 16/8: quantised differences)", 8)
        object.__setattr__(self, "threshold", float(self.threshold))

    def for_field(self, field: str) -> Compression:
        """How ``field``'s messages are encoded: ``inner_bits`` for η and the inner
        tracker."""
        if self.inner_bits is None or field not in INNER_FIELDS:
            return self
        return Compression(threshold=self.threshold, bits=self.inner_bits)

    @property
    def lossless(self) -> bool:
        """The copy equals the value after every message (δ = 0, float64 values)."""
        return self.threshold == 0.0 and self.bits == 64 and self.inner_bits in (None, 64)

    def encode(self, x: torch.Tensor, copy: torch.Tensor) -> bytes:
        """The message that brings ``copy`` ``[s]`` towards ``x`` ``[s]`` (float64)."""
        x, copy = _numpy(x), _numpy(copy)
        diff = x - copy
        selected = (x != copy) if self.threshold == 0.0 else (np.abs(diff) > self.threshold)
        if self.bits >= 32:
            values = x[selected].astype(_VALUE_TYPES[self.bits])
            scale = b""
        else:
            if not selected.any():
                return b""
            level = 2 ** (self.bits - 1) - 1
            scale = _bfloat16_at_least(float(np.abs(diff[selected]).max()))
            q = np.clip(np.rint(diff / _from_bfloat16(scale) * level), -level, level)
            selected &= q != 0
            values = q[selected].astype(_VALUE_TYPES[self.bits])
        n_sent = int(selected.sum())
        if n_sent == 0:
            return b""
        scheme, index = _index(selected, n_sent)
        header = bytes([scheme << 4 | _BITS_CODE[self.bits]])
        return header + index + scale + values.tobytes()

    @staticmethod
    def apply(message: bytes, copy: torch.Tensor) -> tuple[torch.Tensor, int]:
        """``copy`` ``[s]`` after ``message`` (a new float64 tensor) and the number of
        entries the message held. Sender and receivers call this on the same bytes, so
        their copies agree bit for bit."""
        out = _numpy(copy).copy()
        if not message:
            return torch.from_numpy(out), 0
        scheme, bits = message[0] >> 4, _BITS[message[0] & 0xF]
        s, at = out.shape[0], 1
        if scheme == _ALL:
            selected = np.ones(s, dtype=bool)
        elif scheme == _MASK:
            n_bytes = (s + 7) // 8
            selected = np.unpackbits(np.frombuffer(message, np.uint8, n_bytes, at),
                                     count=s).astype(bool)
            at += n_bytes
        else:
            kind = np.dtype("<u2") if scheme == _IDX16 else np.dtype("<u4")
            n_sent = _count(len(message) - at, kind.itemsize, bits, s)
            idx = np.frombuffer(message, kind, n_sent, at)
            selected = np.zeros(s, dtype=bool)
            selected[idx] = True
            at += n_sent * kind.itemsize
        n_sent = int(selected.sum())
        if bits >= 32:
            out[selected] = np.frombuffer(message, _VALUE_TYPES[bits], n_sent, at)
        else:
            level = 2 ** (bits - 1) - 1
            step = _from_bfloat16(message[at:at + 2]) / level
            q = np.frombuffer(message, _VALUE_TYPES[bits], n_sent, at + 2)
            out[selected] += q.astype(np.float64) * step
        return torch.from_numpy(out), n_sent


def _bfloat16_at_least(x: float) -> bytes:
    """The smallest bfloat16 (float32's sign, exponent and top 7 mantissa bits) >= ``x``
    > 0, as 2 little-endian bytes: a quantisation scale only has to bound the entries."""
    bits = int(np.float32(x).view(np.uint32))
    if float(np.float32(x)) < x:
        bits += 1  # float32 rounded down: one ulp up
    if bits & 0xFFFF:
        bits = (bits | 0xFFFF) + 1
    if bits >> 16 >= 0x7F80:
        raise ValueError(f"A difference of {x:g} is beyond the quantisation scale's range.")
    return (bits >> 16).to_bytes(2, "little")


def _from_bfloat16(data: bytes) -> float:
    return float(np.array([int.from_bytes(data, "little") << 16], dtype=np.uint32)
                 .view(np.float32)[0])


def _numpy(x: torch.Tensor) -> np.ndarray:
    return x.detach().to(torch.float64).reshape(-1).numpy()


def _index(selected: np.ndarray, n_sent: int) -> tuple[int, bytes]:
    """The cheapest description of which entries a message holds."""
    s = selected.shape[0]
    if n_sent == s:
        return _ALL, b""
    mask = (s + 7) // 8
    width = 2 if s <= 0xFFFF else 4
    if mask <= width * n_sent:
        return _MASK, np.packbits(selected).tobytes()
    idx = np.flatnonzero(selected).astype("<u2" if width == 2 else "<u4")
    return (_IDX16 if width == 2 else _IDX32), idx.tobytes()


def _count(n_bytes: int, index_size: int, bits: int, s: int) -> int:
    """Entries of an index-list message of ``n_bytes`` after its header."""
    value_size = _VALUE_TYPES[bits].itemsize
    scale = 2 if bits < 32 else 0
    n, rest = divmod(n_bytes - scale, index_size + value_size)
    if rest or not 0 < n <= s:
        raise ValueError(f"A compressed message of {n_bytes + 1} bytes does not fit a "
                         f"vector of {s} entries; the learners disagree on its shape.")
    return n
