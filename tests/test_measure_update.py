"""experiments/studies/measure_update.py times the same update several ways: its ensemble
critics must compute what the separate critics compute (else the comparison is of two
networks), and its Polyak step is SB3's arithmetic (as DecomposedSAC's)."""

from __future__ import annotations

import json
import sys

import torch
from stable_baselines3.common.utils import polyak_update
from studies import measure_update  # experiments/ is on pytest's pythonpath


def test_the_ensemble_critics_are_the_separate_critics_batched():
    torch.manual_seed(0)
    separate = measure_update.SeparateCritics(columns=2)
    ensemble = measure_update.EnsembleCritics(columns=2)
    with torch.no_grad():  # nn.Linear holds W [out, in]; the ensemble W [in, out] per critic
        for k, layer in enumerate([0, 2, 4]):
            for c, net in enumerate(separate.nets):
                ensemble.weights[k][c] = net[layer].weight.T
                ensemble.biases[k][c, 0] = net[layer].bias
    obs, act = torch.randn(7, measure_update.OBS), torch.rand(7, measure_update.ACT)
    torch.testing.assert_close(ensemble(obs, act), separate(obs, act), rtol=1e-5, atol=1e-6)


def test_every_kind_runs_an_update_and_reports(capsys, monkeypatch):
    monkeypatch.setattr(sys, "argv", ["measure_update", "--kinds", "separate", "ensemble",
                                      "lean", "--updates", "3", "--repeat", "1"])
    measure_update.main()
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [line["kind"] for line in lines] == ["separate", "ensemble", "lean"]
    assert all(line["ms_per_update"] > 0 for line in lines)
    # An update trains both networks (it is not a no-op that would time as fast).
    for kind in ("separate", "ensemble", "lean"):  # compile needs a C++ compiler: not here
        update = measure_update.make_update(kind, 2)
        before = [p.detach().clone() for p in (*update.actor.parameters(),
                                                *update.critic.parameters())]
        update(*measure_update.batch(2))
        after = [*update.actor.parameters(), *update.critic.parameters()]
        assert all(not torch.equal(b, a) for b, a in zip(before, after, strict=True)), kind


def test_the_polyak_step_is_sb3s_bit_for_bit():
    torch.manual_seed(0)
    params = [torch.randn(16, 12), torch.randn(16)]
    ours = [torch.randn(16, 12), torch.randn(16)]
    sb3 = [t.clone() for t in ours]
    measure_update.polyak(params, ours, 0.02)
    polyak_update(params, sb3, 0.02)
    assert all(torch.equal(a, b) for a, b in zip(ours, sb3, strict=True))
