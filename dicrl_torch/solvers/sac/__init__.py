"""Entropy-regularised SAC-style constrained solver for continuous multi-agent games
(docs/design.md §5, §7).

The inner problem of D-ICRL needs, for ``η = [ω_r, λ]`` and ``ω_c``, the maximum causal
entropy (MCE) policy of the penalised linear reward

    r(s') = ω_r · φ_r(s') + λ · ω_c · φ_c(s'),

its discounted feature expectations ``μ_r(π) [l_r]`` and ``μ_c(π) [l_c]`` (hence
``J_ωc = ω_c · μ_c``), and the discounted log-likelihood of demonstrations under it.
In a continuous game there is no exact solver; :class:`SACConstrainedSolver`
approximates the MCE policy with stable-baselines3 SAC on a *joint env* (all ``N``
agents as one agent whose action is theirs concatenated), and estimates the
expectations from its own rollouts.

The joint-env protocol
----------------------

The solver builds its envs with ``env_factory(constrained=False)`` (the nominal game it
trains and evaluates in: a learner knows the nominal dynamics, not the constraints) and
``env_factory(constrained=True)`` (the true game of ``evaluate(true_game=True)``, for
metrics). Such an env is a ``gymnasium.Env`` (gymnasium wrappers round it are fine: the
attributes below are looked up through them) with

- ``action_space``: a flat ``Box`` with finite bounds, the agents' actions concatenated
  agent-major (``[N d_a]``); SAC's ``[-1, 1]`` actions are mapped onto it. A discrete
  game is refused (wrap continuous actions instead);
- ``observation_space``: a ``Box``, what the policy and critics read;
- ``n_agents``: ``N``, and ``state_shape``: ``(N, d_s)``;
- ``info["state"]``: the joint state ``[N, d_s]`` (float) after ``reset`` and after
  every ``step``: what the feature bases read (``φ(s')`` of the state a step ended in);
- ``info["reached"]`` and ``info["violated"]`` after every ``step``: ``[N]`` bool, the
  agents that reached their goal / violated a constraint of the game in that step
  (all False where the game has no such notion); the solver ORs them over an episode
  (SR: reached and never violated; CVR: violated);
- ``terminated`` when every agent is done (the final state is then absorbing, below),
  ``truncated`` at a time limit;
- ``obs_from_states(states [..., N, d_s]) -> [..., obs_dim]``: the observation the
  policy would see in a joint state, for scoring and replaying demonstrations
  (:meth:`SACConstrainedSolver.log_likelihood`, ``set_demonstrations``; only needed
  there);
- optionally ``set_rng(rng)``: draw the rest of the episode (its noise) and later
  unseeded resets from ``rng``, so that a :meth:`~SACConstrainedSolver.clone` 's envs
  get streams of their own;
- for an exact :meth:`~SACConstrainedSolver.state_dict`: attributes that are numpy /
  torch / python data (saved by :func:`~dicrl_torch.solvers.sac.state.object_state_dict`),
  or ``state_dict()`` / ``load_state_dict()`` methods of its own.

:class:`dicrl_torch.envs.joint.JointAgentEnv` gives all of this for any PettingZoo
``ParallelEnv`` whose agents have ``Box`` actions (the joint state ``env.state()`` or the
stacked observations; with ``observation="state"`` its observation is the flattened
state, so it rebuilds observations of demonstrated states). A game may also implement
the protocol itself (docs/design.md shows the paper's Table 2 game as one).

Demonstrations are :class:`~dicrl_torch.demos.continuous.ContinuousDemonstrations`
(``states [m, T+1, N, d_s]``, ``actions [m, T, N d_a]`` per agent, ``lengths [m]``,
optionally ``agent_lengths [m, N]``: an agent's actions after it left the episode are
not scored), e.g. from :func:`~dicrl_torch.demos.continuous.record_demonstrations`;
any object with ``to_continuous()`` is converted first. Their shapes are checked
against the env's (the message names the field and the fix).

Design choices, and why
-----------------------

- **Two engines, one algorithm.** The default ``engine="lean"``
  (:mod:`~dicrl_torch.solvers.sac.lean`) collects from the game's own batched env
  (:mod:`dicrl_torch.envs.vector`) and updates networks whose layers are one batched
  product each (:mod:`~dicrl_torch.solvers.sac.networks`,
  :mod:`~dicrl_torch.solvers.sac.update`); ``engine="sb3"``
  (:mod:`~dicrl_torch.solvers.sac.sb3_engine`) is stable-baselines3's loop with the same
  settings, kept as the reference the lean one is tested and benchmarked against
  (``python -m dicrl_torch.bench sac``). Their random draws differ, not their
  arithmetic.
- **No stale rewards.** The replay buffers (:class:`TransitionStore`,
  :class:`FeatureReplayBuffer`) store, per transition, the feature vectors ``φ_r(s')
  [l_r]``, ``φ_c(s') [l_c]`` (and the next state ``[N, d_s]``), never a reward. Rewards
  are computed from the weights set last by ``set_weights``
  (:class:`~dicrl_torch.solvers.sac.labels.RewardLabels`), so after ``η`` or ``ω_c``
  change the whole buffer is relabelled at once and the old experience stays valid
  data.
- **Fixed temperature.** The MCE model is the soft-Bellman policy at temperature 1
  (``π ∝ exp(Q_soft)``, as the grid solver's ``temperature=1``), whose SAC form is the
  objective ``E Σ γ^t (r + α H(π(·|s_t)))`` with ``α = ent_coef = 1``. The temperature
  sets the reward scale that ``η`` is learned at, so it must not move: it is fixed
  (``ent_coef`` a float, no auto-tuning); ``"auto"`` is refused.
- **Warm start.** One SAC model and one buffer live as long as the solver;
  :meth:`SACConstrainedSolver.solve` relabels the buffer and *continues* training
  (``reset_num_timesteps=False``: no new warm-up of random actions, the episodes in
  flight go on), which is what makes thousands of inner iterations affordable.
- **Absorbing termination.** An episode ends (``terminated``) when every agent is done
  (arrived, or frozen in the true game). The grid world lets an expert stay at its
  goal, earning its features until the horizon; here the final state is treated as
  absorbing: the terminal transition earns ``φ(s_L) / (1 - γ)``, the discounted value of
  staying there forever. Without it, a positive reward for being near a goal would
  teach the agents never to arrive (arriving ends the reward stream). Timeouts are
  truncations, bootstrapped by SB3 as usual. The same convention gives the rollout
  and the demonstration feature sums (:func:`discounted_demo_feature_sums`), so the two
  are comparable.
- **Features of the next state.** The reward of transition ``(s_t, a_t, s_{t+1})`` is
  that of ``s_{t+1}``, so the action is credited at once; the discounted sums are
  ``Σ_t γ^t φ(s_{t+1})`` (the initial state's features do not depend on the policy).
- **Private randomness.** The lean engine draws only from generators of its own, seeded
  from ``seed``. SB3 draws from the global torch / numpy / ``random`` generators
  (network init, buffer sampling, action sampling); the SB3 engine owns its own copies
  of those streams and swaps them in only while SB3 runs, restoring the caller's state
  afterwards. Either way: same seed, same numbers, and no global seeding seen from
  outside.
  Evaluation rollouts use an explicit ``torch.Generator`` and ``np.random.Generator``.
- **Exact, pickle-free state.** :meth:`SACConstrainedSolver.state_dict` holds everything
  the next training step, evaluation or likelihood reads (networks, optimisers, the
  engine's counters, the replay buffer, the envs in mid-episode, every random stream) as tensors
  and plain python data: ``torch.load(..., weights_only=True)`` reads it back, and a
  fresh solver built with the same arguments then continues bit for bit as if never
  interrupted. SB3's own ``save`` pickles and is not used.

The package, by responsibility:

- :mod:`~dicrl_torch.solvers.sac.solver`: :class:`SACConstrainedSolver` (training,
  evaluation, likelihood, clones, exact ``state_dict`` / ``load_state_dict``);
  :mod:`~dicrl_torch.solvers.sac.lineages`: its chunked, best-keeping training
  (:class:`Lineage`).
- :mod:`~dicrl_torch.solvers.sac.lean` (:class:`LeanEngine`: the loop),
  :mod:`~dicrl_torch.solvers.sac.networks`, :mod:`~dicrl_torch.solvers.sac.update`
  (:class:`EnsembleSAC`: the update of one or several learners),
  :mod:`~dicrl_torch.solvers.sac.replay` (:class:`TransitionStore`) and
  :mod:`~dicrl_torch.solvers.sac.env_list` (any joint env as a vector env): the lean
  engine. :mod:`~dicrl_torch.solvers.sac.episodes`: the evaluation rollouts (the batched env
  where the game has one). :mod:`~dicrl_torch.solvers.sac.sb3_engine`: the SB3 one.
- :mod:`~dicrl_torch.solvers.sac.protocol`: the checks of the joint-env protocol and
  of the demonstrations against it.
- :mod:`~dicrl_torch.solvers.sac.labels`: the relabelling and demonstrated transitions
  both buffers share; :mod:`~dicrl_torch.solvers.sac.buffer`: :class:`FeatureReplayBuffer`
  (SB3's buffer with features stored, rewards relabelled on sampling).
- :mod:`~dicrl_torch.solvers.sac.solution`: :class:`SACSolution` (rollout estimates).
- :mod:`~dicrl_torch.solvers.sac.features`: the bases' features and agent shares,
  :func:`discounted_demo_feature_sums`, :class:`BoxScaler`.
- :mod:`~dicrl_torch.solvers.sac.decomposed`: :class:`DecomposedSAC` (one soft-Q column
  per agent).
- :mod:`~dicrl_torch.solvers.sac.randomness` and :mod:`~dicrl_torch.solvers.sac.state`:
  the private random streams and the pickle-free state of SB3's model and envs.
  :mod:`~dicrl_torch.solvers.sac.checks`: argument checks.

D-ICRL's adapter over these solvers, ``SACLearnerModel``, lives with the other learner
models in :mod:`dicrl_torch.algos.models`.
"""

from dicrl_torch.solvers.sac.buffer import FeatureReplayBuffer
from dicrl_torch.solvers.sac.decomposed import DecomposedCritic, DecomposedSAC, DecomposedSACPolicy
from dicrl_torch.solvers.sac.features import BoxScaler, discounted_demo_feature_sums
from dicrl_torch.solvers.sac.lean import LeanEngine
from dicrl_torch.solvers.sac.protocol import JointEnvSpec
from dicrl_torch.solvers.sac.replay import TransitionStore
from dicrl_torch.solvers.sac.sb3_engine import SB3Engine
from dicrl_torch.solvers.sac.solution import SACSolution
from dicrl_torch.solvers.sac.solver import STATE_FORMAT, Lineage, SACConstrainedSolver
from dicrl_torch.solvers.sac.update import EnsembleSAC

__all__ = [
    "STATE_FORMAT",
    "BoxScaler",
    "DecomposedCritic",
    "DecomposedSAC",
    "DecomposedSACPolicy",
    "EnsembleSAC",
    "FeatureReplayBuffer",
    "JointEnvSpec",
    "LeanEngine",
    "Lineage",
    "SACConstrainedSolver",
    "SACSolution",
    "SB3Engine",
    "TransitionStore",
    "discounted_demo_feature_sums",
]
