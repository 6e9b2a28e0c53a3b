"""What every algorithm shares: the registry (registry), the typed-config convention and the
trial config builder (config), the learner base (learner: Adam, the gradient step, the update's
number format from precision) and the learner with target networks (target_learner), shared
hyperparameter types (hparams), the recurrent agent network (agent_net), the
batched per-ED heads (branch_heads) and action heads (action_head), the recurrent actor's forward
passes (actor_module), the training loop of the learners from whole episodes
(episode_algorithm), the batch-column names (columns), the episode-metric callbacks (metrics),
torch's per-process settings (torch_process) and decentralised execution, greedy or sampled, of
a trained module (policy)."""
