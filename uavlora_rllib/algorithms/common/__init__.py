"""What every algorithm shares: the registry (registry), the typed-config convention and the
trial config builder (config), the recurrent agent network and action heads (agent_net), the
batch-column names (columns), the episode-metric callbacks (metrics) and decentralised
execution, greedy or sampled, of a trained module (policy)."""
