"""Training's metrics (``train/*``): updates, weights, the data it took or refused, the returns it computed, and each
algorithm's numbers of its last update.

An algorithm's update returns its numbers by name (``policy_loss``); the train service reports each as
``train/<name>`` (``ebrl/services/train.py``), so the module named here is the algorithm's. A user's own algorithm
(``algo.name = "module:Class"``) reports its own names the same way; those are not in this catalog.
"""

from __future__ import annotations

from ebrl.metric import Metric

SERVICE = "services/train.py"
LEARNER = "algos/learner.py"
INTAKE = "algos/intake.py"  # segments taken or refused
RETURNS = "algos/returns.py"  # the episodes' returns, computed by training
PPO = "algos/ppo.py"
ONPOLICY = "algos/onpolicy.py"  # PPO's and GRPO's update around the loss
OFFPOLICY = "algos/offpolicy.py"  # SAC's update: transitions to the replay, gradient steps on its minibatches
SAC = "algos/sac.py"
DEVICES = "devices.py"

METRICS = (
    Metric("train/policy_version", "version", "version published last (every rank reports it; only rank 0 the data "
           "counters)", LEARNER),
    Metric("train/updates", "updates", "updates done", SERVICE, counter=True),
    Metric("train/update_s", "s", "seconds the last update took", SERVICE),
    Metric("train/weights_published", "versions", "weight versions sent", SERVICE, counter=True),
    Metric("train/weights_publish_s", "s", "seconds to pack and send the last version", SERVICE),
    Metric("train/traj_queue", "messages", "trajectory messages received and not yet taken in", SERVICE),
    Metric("train/batch_size", "decisions", "decisions (PPO, GRPO) or transitions (SAC) the last update learned "
           "from", (ONPOLICY, OFFPOLICY)),
    Metric("train/staleness_mean", "versions", "version lag of the last batch's data: mean", (ONPOLICY, OFFPOLICY)),
    Metric("train/staleness_max", "versions", "the same, largest", (ONPOLICY, OFFPOLICY)),
    Metric("train/staleness_hist_<k>", "decisions", "decisions trained on with lag k, since the start", LEARNER),
    Metric("train/stale_dropped", "decisions", "decisions dropped for exceeding `algo.max_staleness`",
           (PPO, "algos/grpo.py"), counter=True),
    Metric("train/pending_steps", "decisions", "decisions buffered for the next batches", LEARNER),
    Metric("train/batch_ready", "0/1", "1 while a full batch waits (the stall watch reads it)", LEARNER),
    Metric("train/segments_received", "segments", "segments taken in", INTAKE, counter=True),
    Metric("train/segments_dropped_overflow", "segments", "segments dropped when over `train.max_pending`", PPO,
           counter=True),
    Metric("train/segments_taken_over", "segments", "segments a stopped train handed over that this one took "
           "(restart, new GPU share)", LEARNER, counter=True),
    Metric("train/env_steps", "steps", "env steps of the segments training took", INTAKE),
    Metric("train/segments_g<group>", "segments", "segments training decoded from group g, taken or not (the stall "
           "watch reads them)", INTAKE),
    Metric("train/future_version_dropped", "segments", "segments acted by a version this train never published "
           "(dropped)", INTAKE, counter=True),
    Metric("train/reward_bound_dropped", "segments", "segments with rewards beyond what a sim clipping at "
           "`env.max_abs_reward` sends (dropped)", INTAKE, counter=True),
    Metric("train/checkpoints", "checkpoints", "checkpoints written", "algos/saving.py", counter=True),
    Metric("train/checkpoints_refused", "checkpoints", "checkpoints not written (non-finite state)",
           "algos/saving.py", counter=True),
    Metric("train/updates_skipped", "steps", "gradient steps skipped, their loss or gradient norm not finite",
           LEARNER, counter=True),
    Metric("train/decisions_dropped", "decisions", "decisions left out of training (advantages, returns or their own "
           "numbers not finite)", (LEARNER, ONPOLICY), counter=True),
    Metric("train/weights_refused", "updates", "updates undone because they made non-finite weights", LEARNER,
           counter=True),
    Metric("train/ranks_checked", "updates", "several training ranks: updates after which the ranks checked they "
           "hold the same weights ([scaling out](scaling-out.md))", LEARNER, counter=True),
    Metric("train/ranks_diverged", "updates", "several training ranks: checks that found the ranks' weights apart",
           LEARNER, counter=True),
    Metric("train/dtype", "bits", "the precision of the matrix products (32: float32, 16: bfloat16 autocast): what "
           "`policy.dtype = \"auto\"` became", LEARNER),
    Metric("train/cuda_device", "index", "the CUDA device training runs on (-1: the CPU)", DEVICES),
    Metric("train/cuda_mem_allocated_mb", "MiB", "on a GPU: memory in use by tensors", DEVICES),
    Metric("train/cuda_mem_reserved_mb", "MiB", "on a GPU: memory held by torch's allocator", DEVICES),
    Metric("train/cuda_mem_cap_mb", "MiB", "on a GPU: the memory cap (the allocator's share, else the device's "
           "memory)", DEVICES),
    # the returns training computed from the rewards and steps it received (ebrl.algos.returns)
    Metric("train/episode_return_mean", "return", "mean return of the latest 20 episodes training counted, computed "
           "by training from the rewards and steps it received (never as a segment reports them): what "
           "`run.target_return` is read from ([security](security.md#what-a-simulator-can-and-cannot-do))", RETURNS),
    Metric("train/success_rate", "fraction", "success rate of the same episodes: what `run.target_success` is read "
           "from", RETURNS),
    Metric("train/episodes", "episodes", "episodes counted", RETURNS),
    Metric("train/episode_length_max", "steps", "the longest episode counted, in env steps", RETURNS),
    Metric("train/episode_values_refused", "segments", "segments refused: their episode's return or length is not "
           "what their rewards and steps make (or a segment that ended no episode claims one)", RETURNS),
    Metric("train/segments_replayed", "segments", "segments refused for repeating steps of an episode training "
           "already had", RETURNS),
    Metric("train/episodes_incomplete", "episodes", "episodes trained on but not counted in the return: a segment "
           "of theirs missing or refused", RETURNS),
    Metric("train/episodes_past_bound", "episodes", "episodes not counted in the return: a reward past "
           "`env.reward_bound`", RETURNS),
    Metric("train/reward_bound", "reward", "the reward bound in force, per env step (absent while an `\"auto\"` "
           "bound is still being learned)", RETURNS),
    # PPO (and GRPO, which trains with PPO's loss): the last update
    Metric("train/policy_loss", "loss", "PPO, GRPO: clipped policy loss of the last update (mean over its gradient "
           "steps)", PPO),
    Metric("train/value_loss", "loss", "PPO: value loss of the last update (GRPO trains no critic)", PPO),
    Metric("train/entropy", "nats", "policy entropy of the last update (SAC: of its gradient steps' actions)",
           (PPO, SAC)),
    Metric("train/approx_kl", "nats", "PPO, GRPO: approximate KL between the policy before and after the last "
           "update", PPO),
    Metric("train/clipfrac", "fraction", "PPO, GRPO: share of the last update's ratios clipped", PPO),
    Metric("train/behave_weight_mean", "ratio", "decoupled PPO: mean pi_prox / pi_behave weight of the last update "
           "(1 when on-policy)", PPO),
    Metric("train/behave_kl", "nats", "decoupled PPO: KL(pi_behave ‖ pi_prox) of the last update (k3 estimator, 0 "
           "on-policy)", PPO),
    Metric("train/behave_weight_capped", "fraction", "decoupled PPO: share of pi_prox / pi_behave weights above "
           "`algo.behave_weight_cap`", PPO),
    Metric("train/behave_weight_max", "ratio", "decoupled PPO: the largest pi_prox / pi_behave weight", PPO),
    Metric("train/value_drift", "value", "RMS of (current - behaviour) critic values over the last batch (how far "
           "the critic moved since the data was acted)", PPO),
    Metric("train/explained_variance", "fraction", "1 - Var(returns - values) / Var(returns) of the last batch",
           PPO),
    Metric("train/adv_mean", "value", "mean of the last batch's raw advantages (before per-minibatch "
           "normalisation)", PPO),
    Metric("train/adv_std", "value", "their standard deviation", PPO),
    # GRPO
    Metric("train/grpo_groups", "groups", "GRPO: complete groups", "algos/grpo.py", counter=True),
    Metric("train/grpo_groups_dropped_overflow", "groups", "GRPO: groups dropped over `train.max_pending`",
           "algos/grpo.py", counter=True),
    Metric("train/grpo_episodes_incomplete", "episodes", "GRPO: episodes with a missing segment, dropped",
           "algos/grpo.py", counter=True),
    # SAC ([Algorithms](algorithms.md#sac))
    Metric("train/critic_loss", "loss", "SAC: critics' loss, mean over the last update's gradient steps", SAC),
    Metric("train/actor_loss", "loss", "SAC: actor's loss, the same", SAC),
    Metric("train/alpha_loss", "loss", "SAC: the entropy temperature's loss, the same", SAC),
    Metric("train/alpha", "value", "SAC: the entropy temperature", OFFPOLICY),
    Metric("train/q_mean", "value", "SAC: mean of min(Q1, Q2) over the last update's minibatches", SAC),
    Metric("train/gradient_steps", "steps", "SAC: the gradient steps the last update took", OFFPOLICY),
    Metric("train/gradient_steps_total", "steps", "SAC: gradient steps so far", OFFPOLICY),
    Metric("train/utd", "ratio", "SAC: gradient steps per env step since learning started (`algo.utd` is the "
           "target)", OFFPOLICY),
    Metric("train/replay_sent", "transitions", "SAC: transitions sent to the replay service", OFFPOLICY),
    Metric("train/replay_wait_s", "s", "SAC: seconds updates waited for the replay's minibatches",
           "algos/replaylink.py", counter=True),
    Metric("train/replay_resent", "requests", "SAC: requests sent again (no answer in 5 s: a replay restarting)",
           "algos/replaylink.py", counter=True),
    Metric("train/replay_refused", "answers", "SAC: answers that did not fit their request, asked for again",
           "algos/replaylink.py", counter=True),
)
