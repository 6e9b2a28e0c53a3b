"""The experiment layer: the grid schema, the execution-phase evaluation and MLflow tracking."""
