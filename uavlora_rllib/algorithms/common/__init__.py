"""What every algorithm shares: the registry, the recurrent agent network and the greedy policy."""
