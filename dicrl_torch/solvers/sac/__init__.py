"""Entropy-regularised SAC-style constrained solver for the drone arena (docs/design.md §5, §7).

The inner problem of D-ICRL needs, for ``η = [ω_r, λ]`` and ``ω_c``, the maximum causal
entropy (MCE) policy of the penalised linear reward

    r(s') = ω_r · φ_r(s') + λ · ω_c · φ_c(s'),

its discounted feature expectations ``μ_r(π) [l_r]`` and ``μ_c(π) [l_c]`` (hence
``J_ωc = ω_c · μ_c``), and the discounted log-likelihood of demonstrations under it.
In the continuous arena there is no exact solver; :class:`SACConstrainedSolver`
approximates the MCE policy with stable-baselines3 SAC on :class:`JointDroneEnv`
(both drones as one agent, action ``[4]``), and estimates the expectations from its own
rollouts.

Design choices, and why:

- **No stale rewards.** :class:`FeatureReplayBuffer` stores, per transition, the feature
  vectors ``φ_r(s') [l_r]``, ``φ_c(s') [l_c]`` (and the next state ``[2, 4]``), never a
  reward. :meth:`FeatureReplayBuffer.sample` computes the rewards from the weights set
  last by :meth:`FeatureReplayBuffer.set_weights`, so after ``η`` or ``ω_c`` change the
  whole buffer is relabelled at once and the old experience stays valid data.
- **Fixed temperature.** The MCE model is the soft-Bellman policy at temperature 1
  (``π ∝ exp(Q_soft)``, as the grid solver's ``temperature=1``), whose SAC form is the
  objective ``E Σ γ^t (r + α H(π(·|s_t)))`` with ``α = ent_coef = 1``. The temperature
  sets the reward scale that ``η`` is learned at, so it must not move: it is fixed
  (``ent_coef`` a float, no auto-tuning); ``"auto"`` is refused.
- **Warm start.** One SAC model and one buffer live as long as the solver;
  :meth:`SACConstrainedSolver.solve` relabels the buffer and *continues* training
  (``reset_num_timesteps=False``: no new warm-up of random actions, the episodes in
  flight go on), which is what makes thousands of inner iterations affordable.
- **Absorbing termination.** An episode of :class:`JointDroneEnv` ends when no drone
  flies (all arrived, or frozen in the true game). The grid world lets an expert stay at
  its goal, earning its features until the horizon; here the final state is treated as
  absorbing: the terminal transition earns ``φ(s_L) / (1 - γ)``, the discounted value of
  staying there forever. Without it, a positive reward for being near the door would
  teach the drones never to arrive (arriving ends the reward stream). Timeouts
  (``max_steps``) are truncations, bootstrapped by SB3 as usual. The same convention
  gives the rollout and the demonstration feature sums
  (:func:`discounted_demo_feature_sums`), so the two are comparable.
- **Features of the next state.** The reward of transition ``(s_t, a_t, s_{t+1})`` is
  that of ``s_{t+1}``, so the action is credited at once; the discounted sums are
  ``Σ_t γ^t φ(s_{t+1})`` (the initial state's features do not depend on the policy).
- **Private randomness.** SB3 draws from the global torch / numpy / ``random``
  generators (network init, buffer sampling, action sampling). The solver owns its
  own copies of those streams, seeded from ``seed``, and swaps them in only while SB3
  runs (:meth:`SACConstrainedSolver._private_rng`), restoring the caller's state
  afterwards: same seed, same numbers, and no global seeding seen from outside.
  Evaluation rollouts use an explicit ``torch.Generator`` and ``np.random.Generator``.
- **Exact, pickle-free state.** :meth:`SACConstrainedSolver.state_dict` holds everything
  the next ``learn()``, evaluation or likelihood reads (networks, optimisers, SB3's
  counters, the replay buffer, the envs in mid-episode, every random stream) as tensors
  and plain python data: ``torch.load(..., weights_only=True)`` reads it back, and a
  fresh solver built with the same arguments then continues bit for bit as if never
  interrupted. SB3's own ``save`` pickles and is not used.

The package, by responsibility:

- :mod:`~dicrl_torch.solvers.sac.solver`: :class:`SACConstrainedSolver` (training,
  evaluation, likelihood, clones, exact ``state_dict`` / ``load_state_dict``).
- :mod:`~dicrl_torch.solvers.sac.buffer`: :class:`FeatureReplayBuffer` (features stored,
  rewards relabelled on sampling, demonstrations mixed in).
- :mod:`~dicrl_torch.solvers.sac.solution`: :class:`SACSolution` (rollout estimates).
- :mod:`~dicrl_torch.solvers.sac.features`: joint observations, the bases' features,
  :func:`discounted_demo_feature_sums`, :class:`BoxScaler`.
- :mod:`~dicrl_torch.solvers.sac.decomposed`: :class:`DecomposedSAC` (one soft-Q column
  per drone).
- :mod:`~dicrl_torch.solvers.sac.randomness` and :mod:`~dicrl_torch.solvers.sac.state`:
  the private random streams and the pickle-free state of SB3's model and envs.
  :mod:`~dicrl_torch.solvers.sac.checks`: argument checks.

D-ICRL's adapter over these solvers, ``SACLearnerModel``, lives with the other learner
models in :mod:`dicrl_torch.algos.models`.
"""

from dicrl_torch.solvers.sac.buffer import FeatureReplayBuffer
from dicrl_torch.solvers.sac.decomposed import DecomposedCritic, DecomposedSAC, DecomposedSACPolicy
from dicrl_torch.solvers.sac.features import (
    BoxScaler,
    discounted_demo_feature_sums,
    joint_obs_from_states,
)
from dicrl_torch.solvers.sac.solution import SACSolution
from dicrl_torch.solvers.sac.solver import STATE_FORMAT, SACConstrainedSolver

__all__ = [
    "STATE_FORMAT",
    "BoxScaler",
    "DecomposedCritic",
    "DecomposedSAC",
    "DecomposedSACPolicy",
    "FeatureReplayBuffer",
    "SACConstrainedSolver",
    "SACSolution",
    "discounted_demo_feature_sums",
    "joint_obs_from_states",
]
