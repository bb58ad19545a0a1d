"""experiments/studies/bootstrap_certificate.py on the shared TINY run: refit 0 trains the
run's C-ICRL again (its reward and certified set), and a resample draws whole trajectories
with replacement."""

from __future__ import annotations

import json
import shutil

import numpy as np
from omegaconf import OmegaConf
from studies.bootstrap_certificate import main, resample

from dicrl_torch.demos.storage import Demonstrations


def study(tiny_reference, tmp_path, capsys, *args) -> list[dict]:
    """The study's printed JSON lines on a copy of the TINY run."""
    # an in-process run writes no .hydra/: the study reads the config results.json holds
    run = tmp_path / "run"
    shutil.copytree(tiny_reference, run)
    (run / ".hydra").mkdir()
    config = json.loads((run / "results.json").read_text())["config"]
    OmegaConf.save(OmegaConf.create(config), run / ".hydra" / "config.yaml")
    main([str(run), *args])
    return [json.loads(line) for line in capsys.readouterr().out.splitlines()
            if line.startswith("{")]


def test_refit_0_trains_the_runs_c_icrl_again(tiny_reference, tmp_path, capsys):
    printed = study(tiny_reference, tmp_path, capsys, "--refits", "0")
    row = json.loads((tiny_reference / "results.json").read_text())
    row = row["methods"]["C-ICRL"]["learners"][0]
    assert len(printed) == 1 and printed[0]["refit"] == 0
    assert printed[0]["constraints"] == row["constraints"]
    assert printed[0]["RFD"] == row["RFD"]
    assert abs(printed[0]["eta_bar"][-1] - row["multiplier"]) < 6e-4  # rounded to 3 decimals


def test_local_refits_certify_a_reward_of_their_own_resample(tiny_reference, tmp_path,
                                                              capsys):
    """``--local``: one line per refit, the same resample giving the same reward and set
    (the trained C-ICRL is each refit's warm start, whatever came before)."""
    printed = study(tiny_reference, tmp_path, capsys, "--refits", "1,0,1", "--local")
    assert [p["refit"] for p in printed] == [1, 0, 1]
    for key in ("eta_bar", "constraints", "FPR", "RFD"):
        assert printed[0][key] == printed[2][key], key
    assert all(isinstance(p["constraints"], list) and len(p["eta_bar"]) == 3
               for p in printed)


def test_a_resample_draws_whole_trajectories_with_replacement():
    rng = np.random.default_rng(5)
    states = rng.integers(0, 9, size=(12, 5, 1))
    demos = Demonstrations(states=states, actions=rng.integers(0, 4, size=(12, 4, 1)),
                           n_cells=9, n_actions=4)
    assert resample(demos, 0) is demos
    drawn = resample(demos, 3)
    assert drawn.states.shape == demos.states.shape
    def trajectories(d):
        return [(s.tobytes(), a.tobytes()) for s, a in zip(d.states, d.actions, strict=True)]

    originals, pairs = set(trajectories(demos)), trajectories(drawn)
    assert set(pairs) <= originals
    assert len(set(pairs)) < len(pairs)  # with replacement: this draw repeats one
    assert resample(demos, 3).states.tolist() == drawn.states.tolist()  # seeded
