"""Old home of the MLflow tracking code, now in `run_schema`, `mlflow_client` and `mlflow_callback`.

Kept for one name only: Tune pickles the run config, callbacks included, into ``tuner.pkl``,
and `Tuner.restore` (``--resume``) unpickles it by class path, so experiments started before
the split refer to ``uavlora_rllib.experiment.tracking.MlflowTrialCallback``.
"""

from uavlora_rllib.experiment.mlflow_callback import MlflowTrialCallback  # noqa: F401
