"""One-off studies and measurements behind the numbers in docs/, kept apart from the entry
points of ``experiments/`` (``train.py``, ``demo_foundation.py``, ``summarize.py``,
``tb_snapshot.py``). They use the library's public API only. Run each from the repository
root as a script, ``.venv/bin/python experiments/studies/NAME.py [args]``; its docstring
gives examples and says what it prints.

- ``bootstrap_certificate.py``: C-ICRL's certificate on resampled demonstrations of a
  finished grid run (each refit trained from scratch, or ``--local`` from the warm start).
- ``identifiability.py``: which true grid constraints the demonstrations determine
  (demonstrated / required / undetermined), time per candidate, and the likelihoods of
  alternative walls.
- ``measure_greedy.py``: ME- and MCE-greedy on the grid world: FPR, FNR, recovered
  constraints, wall time, CR / CVR (``--one-step``: time one greedy step).
- ``measure_sac.py``: the SAC solver's env steps/s and gradient updates/s.
- ``measure_update.py``: ms per SAC update, critics as separate, batched or compiled nets.
- ``measure_planner.py``: SR, CVR and speed of planning on the true drone game
  (``solver.eval_policy=plan``), with a checksum of the flights.
- ``prune_study.py``: for each learned drone constraint of a finished run, how many plans
  enter it once it is removed from the learned game.
- ``resolve_study.py``: re-solves on a finished SAC run's checkpoint (``prune``: visits of
  each freed feature; ``last-solve``: one learner's last solve with changed settings).

``bootstrap_certificate``, ``measure_planner``, ``prune_study`` and ``resolve_study`` build
the task from a config as ``train.py`` does, with ``experiments/common.py``: each puts
``experiments/`` on ``sys.path`` itself (one line before ``from common import ...``), so it
runs from any directory. The tests import them as ``studies.NAME`` (pytest's ``pythonpath`` holds
``experiments``).
"""
