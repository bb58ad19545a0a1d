"""experiments/summarize.py: mean ± std across a multirun's results.json files."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))
import summarize  # noqa: E402


def write_run(root: Path, seed: int, cr: float, fpr: float, experiment="quick") -> None:
    row = {"CR_mean": cr, "CR_std": 1.0, "FPR": fpr, "FNR": 0.5, "CVR": 0.0, "RFD": 1.0}
    expert = {**row, "FPR": None, "FNR": None, "RFD": 0.0}
    d = root / f"seed={seed}"
    d.mkdir(parents=True)
    (d / "results.json").write_text(json.dumps({"experiment": experiment, "methods": {
        "D-ICRL": {"learners": [row, row]}, "Experts (ground truth)": {"learners": [expert]}}}))


def test_mean_and_sample_std_per_row(tmp_path, capsys):
    write_run(tmp_path, 0, cr=10.0, fpr=0.0)
    write_run(tmp_path, 1, cr=14.0, fpr=0.5)
    summarize.main([str(tmp_path)])
    out = json.loads((tmp_path / "summary.json").read_text())["rows"]
    assert list(out) == ["D-ICRL 1", "D-ICRL 2", "Experts (ground truth)"]
    mean, std = out["D-ICRL 1"]["CR_mean"]
    assert mean == 12.0 and math.isclose(std, math.sqrt(8.0))
    assert out["Experts (ground truth)"]["FPR"] is None
    assert out["D-ICRL 1"]["FNR_required"] is None  # these runs predate the column
    printed = capsys.readouterr().out
    assert "12.000 ± 2.828" in printed
    assert "SR" not in printed.splitlines()[1]  # a column no row has is not printed


def test_drone_rows_get_success_rate(tmp_path, capsys):
    for seed, sr in ((0, 1.0), (1, 0.5)):
        d = tmp_path / f"seed={seed}"
        d.mkdir()
        row = {"SR": sr, "CVR": 1 - sr, "FPR": 0.0, "FNR": 0.0}
        (d / "results.json").write_text(json.dumps(
            {"experiment": "table2", "methods": {"C-ICRL": {"learners": [row]}}}))
    summarize.main([str(tmp_path)])
    out = json.loads((tmp_path / "summary.json").read_text())["rows"]
    assert out["C-ICRL"]["SR"] == [0.75, math.sqrt(0.125)]
    assert out["C-ICRL"]["CR_mean"] is None
    header = capsys.readouterr().out.splitlines()[1].split()
    assert header == ["SR", "FPR", "FNR", "CVR"]


def test_mixed_experiments_and_empty_directories_are_refused(tmp_path):
    with pytest.raises(SystemExit, match="No results.json"):
        summarize.main([str(tmp_path)])
    write_run(tmp_path, 0, 1.0, 0.0)
    write_run(tmp_path, 1, 1.0, 0.0, experiment="table1_small")
    with pytest.raises(SystemExit, match="different experiments"):
        summarize.main([str(tmp_path)])
