"""What every algorithm shares: the registry (registry), the typed-config convention and the
trial config builder (config), the recurrent agent network and action heads (agent_net), the
recurrent actor's forward passes (actor_module), the training loop of the learners from whole
episodes (episode_algorithm), the learner with target networks (target_learner), the
batch-column names (columns), the episode-metric callbacks (metrics), torch's thread count
(threads) and decentralised execution, greedy or sampled, of a trained module (policy)."""
