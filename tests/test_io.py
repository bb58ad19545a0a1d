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
