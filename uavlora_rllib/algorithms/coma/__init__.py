"""COMA: GRU actors with a counterfactual centralised critic."""
