"""Are the grid world's constraints identifiable from the experts' demonstrations?

    .venv/bin/python experiments/studies/identifiability.py              # 2 experts (quick)
    .venv/bin/python experiments/studies/identifiability.py --experts 1
    .venv/bin/python experiments/studies/identifiability.py --all        # every feature of U
    .venv/bin/python experiments/studies/identifiability.py --experts 3 --time-one
    .venv/bin/python experiments/studies/identifiability.py --basis regions --no-likelihood
    .venv/bin/python experiments/studies/identifiability.py --varied --no-likelihood  # varied

**Classes** (docs/design.md §6, :mod:`dicrl_torch.algos.identifiability`). The true
constraints of the cost basis (``--all``: every feature) are classified as
*demonstrated* (some demonstration, or P0, accrues them), *required* (undemonstrated, and
the experts, with every other undemonstrated feature forbidden, still accrue them with
probability >= 0.01 per trajectory) or *undetermined*, with the time per candidate (one
backward solve and an exact forward pass). ``--time-one`` classifies a single true
constraint only, to time one candidate where a full classification is long (3 experts).
``--varied`` samples the demonstrations under the varied-start protocol (docs/design.md
§3: ``GridLayout.scobee_varied``, each expert's start uniform over the free cells of its
rectangle of ``SCOBEE_START_REGIONS``; ``--start-regions "x0,y0,x1,y1;..."`` sets them) and
classifies with that P0.

**Likelihoods.** Compares the demonstrations' mean log-likelihood (nats per trajectory,
the D-ICRL objective's γ-discounted convention) under the *true* reward, scaled by ``s``
(the soft-optimal MCE model at temperature ``1/s``), with two constraint sets enforced as
hard masks:

- the true set (obstacles, NE/NW, collision), and
- an alternative in which the bottom of the x = 4 wall, (4,5)–(4,8), is replaced by a
  wall at x = 2 (cells (2,4)–(2,8)) plus (3,5), sealing the pocket below the chevron.

No optimal expert ever enters that pocket: it is a dead end once the chevron and the
forbidden NE move are in place, so the demonstrations cannot tell the two walls apart.
Equal likelihoods mean that no maximum-likelihood learner, D-ICRL or greedy, can prefer
the true wall from these data; FPR and FNR then depend on tie-breaking. The script also
reports the likelihood of the alternative in which the top of the wall, (4,0)–(4,2), is
moved to (5,0), (5,1), (6,0), which the data do rule out. (Shared basis only.)
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
import torch

from dicrl_torch.algos.greedy import constraint_masks
from dicrl_torch.algos.icrl import log_likelihood
from dicrl_torch.algos.identifiability import classify_features
from dicrl_torch.envs.grid import GridLayout, TabularGridModel
from dicrl_torch.features.bases import (
    GoalClosenessRewardBasis,
    PerExpertIndicatorCostBasis,
    RegionIndicatorCostBasis,
    SharedIndicatorCostBasis,
)
from dicrl_torch.solvers.experts import expert_solution, sample_trajectories
from dicrl_torch.solvers.factored import FactoredSoftBellman

BOTTOM_WALL = ("cell(4,5)", "cell(4,6)", "cell(4,7)", "cell(4,8)")
POCKET_WALL = ("cell(2,4)", "cell(2,5)", "cell(2,6)", "cell(2,7)", "cell(2,8)", "cell(3,5)")
TOP_WALL = ("cell(4,0)", "cell(4,1)", "cell(4,2)")
TOP_RIGHT = ("cell(5,0)", "cell(5,1)", "cell(6,0)")
BASES = {"shared": SharedIndicatorCostBasis, "per_expert": PerExpertIndicatorCostBasis,
         "regions": RegionIndicatorCostBasis}


def classify(args, solver, reward, cost_basis, demos) -> None:
    true = cost_basis.true_constraints()
    only = None if args.all else true
    if args.time_one:  # one candidate: the first true constraint
        only = torch.zeros_like(true)
        only[int(torch.nonzero(true)[0])] = True
    result = classify_features(solver=solver, reward=reward, cost_basis=cost_basis,
                               demonstrations=demos, temperature=args.expert_temperature,
                               initial_distribution=solver.model.initial_distribution(),
                               only=only, progress=args.progress)
    per = result.seconds_per_candidate
    print(f"\nidentifiability ({args.basis} basis, {args.demonstrations} demonstrations, "
          f"expert temperature {args.expert_temperature:g}): {result.n_solves} candidate(s) "
          f"in {result.seconds:.1f} s" + (f", {per:.2f} s per candidate" if per else ""))
    if args.time_one:
        return
    if args.all:
        print(f"  all features: {result.summary()}")
    t = result.restrict(true)
    print(f"  true constraints: {t.n_features} = {t.n_demonstrated} demonstrated + "
          f"{t.n_required} required + {t.n_undetermined} undetermined")
    for label, mask in (("demonstrated", t.demonstrated), ("required", t.required),
                        ("undetermined", t.undetermined)):
        cols = [n + ("" if label == "demonstrated" else
                     f" ({float(t.probability[t.names.index(n)]):.3g})")
                for n in t.names_of(mask)]
        print(f"  {label:13s} {', '.join(cols) or '-'}")


def likelihoods(args, solver, reward_basis, cost_basis, demos, model) -> None:
    phi_r, phi_c = reward_basis(), cost_basis()
    w_true = reward_basis.true_weights()
    names = cost_basis.names
    true = [names[j] for j in torch.nonzero(cost_basis.true_constraints()).flatten()]
    pocket = [n for n in true if n not in BOTTOM_WALL] + list(POCKET_WALL)
    both = [n for n in pocket if n not in TOP_WALL] + list(TOP_RIGHT)
    sets = {"true set": true, "x=2 pocket wall": pocket, "pocket + top-right": both}

    print(f"\n{args.experts} expert(s), {args.demonstrations} demonstrations; mean "
          f"log-likelihood per trajectory under the true reward x s")
    print(f"{'s':>4s}" + "".join(f"{k + f' ({len(v)})':>26s}" for k, v in sets.items()))
    for scale in (float(s) for s in args.scales.split(",")):
        row = []
        for members in sets.values():
            selected = torch.zeros(cost_basis.dim, dtype=torch.bool)
            selected[[names.index(n) for n in members]] = True
            mask, terminal = constraint_masks(phi_c, selected, model)
            sol = solver.solve(phi_r.weighted(w_true * scale) + mask, forward=False,
                               terminal_value=terminal)
            row.append(log_likelihood(sol, demos) / demos.n_trajectories)
        print(f"{scale:4g}" + "".join(f"{x:26.4f}" for x in row))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--experts", type=int, default=2)
    parser.add_argument("--demonstrations", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--horizon", type=int, default=40)
    parser.add_argument("--gamma", type=float, default=0.99)
    parser.add_argument("--expert-temperature", type=float, default=0.0)
    parser.add_argument("--basis", choices=sorted(BASES), default="shared")
    parser.add_argument("--all", action="store_true",
                        help="classify every feature, not only the true constraints")
    parser.add_argument("--time-one", action="store_true",
                        help="classify one true constraint only (time one candidate)")
    parser.add_argument("--no-likelihood", action="store_true")
    parser.add_argument("--scales", default="1,5,20")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--dtype", default="float64", choices=("float32", "float64"))
    parser.add_argument("--progress", action="store_true")
    parser.add_argument("--varied", action="store_true",
                        help="varied starts (SCOBEE_START_REGIONS for the number of experts)")
    parser.add_argument("--start-regions", default=None,
                        help="varied starts in these rectangles: 'x0,y0,x1,y1;...', one per "
                             "expert")
    args = parser.parse_args()
    if "DICRL_THREADS" in os.environ:
        torch.set_num_threads(int(os.environ["DICRL_THREADS"]))

    if args.start_regions is not None:
        regions = [[int(v) for v in r.split(",")] for r in args.start_regions.split(";")]
        layout = GridLayout.scobee_varied(n_experts=args.experts, start_regions=regions)
    elif args.varied:
        layout = GridLayout.scobee_varied(n_experts=args.experts)
    else:
        layout = GridLayout.scobee(n_experts=args.experts)
    model = TabularGridModel(layout=layout, horizon=args.horizon, gamma=args.gamma)
    solver = FactoredSoftBellman(model=model, dtype=args.dtype, device=args.device)
    reward_basis, cost_basis = GoalClosenessRewardBasis(model), BASES[args.basis](model)
    w_true = reward_basis.true_weights()
    t0 = time.perf_counter()
    experts = expert_solution(solver=solver, reward_features=reward_basis(),
                              reward_weights=w_true, temperature=args.expert_temperature)
    demos = sample_trajectories(experts, args.demonstrations,
                                np.random.default_rng(args.seed))
    starts = ("fixed starts" if layout.start_sets is None else "varied starts over " +
              ", ".join(f"{len(s)}" for s in layout.start_sets) + " cells")
    print(f"{args.experts} expert(s), {starts}, T={args.horizon}, γ={args.gamma}, "
          f"{args.demonstrations} demonstrations (seed {args.seed}); experts solved and "
          f"sampled in {time.perf_counter() - t0:.1f} s")
    classify(args, solver, reward_basis().weighted(w_true), cost_basis, demos)
    if not args.no_likelihood and args.basis == "shared":
        likelihoods(args, solver, reward_basis, cost_basis, demos, model)


if __name__ == "__main__":
    main()
