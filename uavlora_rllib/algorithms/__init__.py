"""RLlib algorithms written for this project (ray 2.60 ships none of them)."""
