"""results.json's writer: atomic, and JSON that reads back as ``json.dumps`` would."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from dicrl_torch.io import dumps_compact, write_json


def test_compact_json_reads_back_as_json_dumps():
    obj = {"scalars": [1, 2.5, None, "x]", True, 1e-300], "empty": {}, "none": [],
           "nested": [[1, 2], [3.0]], "rows": [{"SR": 0.97, "names": ["a", "b"]}],
           3: "int key", True: "bool key", None: "none key", 0.5: "float key",
           "tuple": (1, 2), "nan": math.nan, "deep": {"a": {"b": [[{"c": []}]]}}}
    text = dumps_compact(obj)
    got, want = json.loads(text), json.loads(json.dumps(obj))
    assert math.isnan(got.pop("nan")) and math.isnan(want.pop("nan"))
    assert got == want
    # a list of scalars is one line; a list holding a list is not
    assert '"scalars": [1, 2.5, null, "x]", true, 1e-300]' in text
    assert '"nested": [\n' in text
    assert dumps_compact([]) == "[]" and dumps_compact({}) == "{}"


def test_a_value_json_cannot_hold_writes_nothing(tmp_path):
    path = tmp_path / "results.json"
    write_json(path, {"SR": 1.0})
    for bad in ({"SR": np.int64(1)}, {(1, 2): 0.5}):
        with pytest.raises(TypeError):
            write_json(path, bad)
    assert json.loads(path.read_text()) == {"SR": 1.0}
    assert [p.name for p in tmp_path.iterdir()] == ["results.json"]  # no temporary left


class _Stop(Exception):
    pass


def _raise_stop(signum, frame):
    raise _Stop(signum)


def test_a_signal_during_torch_save_is_handled_once_the_file_is_in_place(tmp_path):
    """SIGINT raised by a handler mid-torch.save became torch's RuntimeError ("unexpected
    pos") and no file; held by atomic_write, the handler's own exception comes after the
    whole file is in place, and the handlers are the caller's again."""
    import os
    import signal

    import torch

    from dicrl_torch.io import atomic_write

    class SignalOnSecondWrite:
        def __init__(self, f):
            self.f, self.writes = f, 0

        def write(self, b):
            self.writes += 1
            if self.writes == 2:
                os.kill(os.getpid(), signal.SIGINT)
            return self.f.write(b)

        def flush(self):
            return self.f.flush()

    state = {"w": torch.arange(50_000.0)}
    before = signal.signal(signal.SIGINT, _raise_stop)
    try:
        with pytest.raises(_Stop):
            atomic_write(tmp_path / "c.pt", lambda f: torch.save(state, SignalOnSecondWrite(f)))
        assert signal.getsignal(signal.SIGINT) is _raise_stop
    finally:
        signal.signal(signal.SIGINT, before)
    assert torch.equal(torch.load(tmp_path / "c.pt", weights_only=True)["w"], state["w"])
    assert [p.name for p in tmp_path.iterdir()] == ["c.pt"]  # no temporary file left


def test_a_failing_write_still_leaves_the_old_file_and_no_signal_is_swallowed(tmp_path):
    import os
    import signal

    from dicrl_torch.io import atomic_write

    (tmp_path / "f").write_bytes(b"old")

    def fails(f):
        f.write(b"half")
        os.kill(os.getpid(), signal.SIGINT)
        raise OSError("disk full")

    before = signal.signal(signal.SIGINT, _raise_stop)
    try:
        with pytest.raises(_Stop):  # the signal, after the cleanup
            atomic_write(tmp_path / "f", fails)
    finally:
        signal.signal(signal.SIGINT, before)
    assert (tmp_path / "f").read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["f"]
