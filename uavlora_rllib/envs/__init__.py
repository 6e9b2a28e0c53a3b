"""Environment views of the simulator: per-UAV agents (PettingZoo, RLlib) and the team view."""
