"""Are the grid world's constraints identifiable from the experts' demonstrations?

    .venv/bin/python experiments/identifiability.py                 # 2 experts (quick)
    .venv/bin/python experiments/identifiability.py --experts 1

Compares the demonstrations' mean log-likelihood (nats per trajectory, the D-ICRL
objective's γ-discounted convention) under the *true* reward, scaled by ``s`` (the
soft-optimal MCE model at temperature ``1/s``), with two constraint sets enforced as
hard masks:

- the true set (obstacles, NE/NW, collision), and
- an alternative in which the bottom of the x = 4 wall, (4,5)–(4,8), is replaced by a
  wall at x = 2 (cells (2,4)–(2,8)) plus (3,5), sealing the pocket below the chevron.

No optimal expert ever enters that pocket: it is a dead end once the chevron and the
forbidden NE move are in place, so the demonstrations cannot tell the two walls apart.
Equal likelihoods mean that no maximum-likelihood learner, D-ICRL or greedy, can prefer
the true wall from these data; FPR and FNR then depend on tie-breaking. The script also
reports the likelihood of the alternative in which the top of the wall, (4,0)–(4,2), is
moved to (5,0), (5,1), (6,0), which the data do rule out.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from dicrl_torch.algos.greedy import constraint_masks
from dicrl_torch.algos.icrl import log_likelihood
from dicrl_torch.envs.grid import GridLayout, TabularGridModel
from dicrl_torch.features.bases import GoalClosenessRewardBasis, SharedIndicatorCostBasis
from dicrl_torch.solvers.experts import expert_solution, sample_trajectories
from dicrl_torch.solvers.factored import FactoredSoftBellman

BOTTOM_WALL = ("cell(4,5)", "cell(4,6)", "cell(4,7)", "cell(4,8)")
POCKET_WALL = ("cell(2,4)", "cell(2,5)", "cell(2,6)", "cell(2,7)", "cell(2,8)", "cell(3,5)")
TOP_WALL = ("cell(4,0)", "cell(4,1)", "cell(4,2)")
TOP_RIGHT = ("cell(5,0)", "cell(5,1)", "cell(6,0)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--experts", type=int, default=2)
    parser.add_argument("--demonstrations", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--scales", default="1,5,20")
    args = parser.parse_args()

    layout = GridLayout.scobee(n_experts=args.experts)
    model = TabularGridModel(layout=layout, horizon=40, gamma=0.99)
    solver = FactoredSoftBellman(model=model, dtype=torch.float64)
    reward_basis, cost_basis = GoalClosenessRewardBasis(model), SharedIndicatorCostBasis(model)
    phi_r, phi_c = reward_basis(), cost_basis()
    w_true = reward_basis.true_weights()
    experts = expert_solution(solver=solver, reward_features=phi_r, reward_weights=w_true)
    demos = sample_trajectories(experts, args.demonstrations, np.random.default_rng(args.seed))

    names = cost_basis.names
    true = [names[j] for j in torch.nonzero(cost_basis.true_constraints()).flatten()]
    pocket = [n for n in true if n not in BOTTOM_WALL] + list(POCKET_WALL)
    both = [n for n in pocket if n not in TOP_WALL] + list(TOP_RIGHT)
    sets = {"true set": true, "x=2 pocket wall": pocket, "pocket + top-right": both}

    print(f"{args.experts} expert(s), {args.demonstrations} optimal demonstrations; mean "
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


if __name__ == "__main__":
    main()
