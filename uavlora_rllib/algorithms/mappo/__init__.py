"""MAPPO (centralised critic on the global state, GRU actors) and IPPO (local critic)."""
