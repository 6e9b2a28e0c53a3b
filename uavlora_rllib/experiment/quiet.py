"""Silence the library messages every grid prints and that need no action from the user.

Each entry names its source and why it is harmless here. The filters match the message text
exactly enough that a new, different message from the same logger still shows.

* RLlib's "You are running X on the new API stack!" notice (algorithm_config.py): the
  project's algorithms are new-API-stack only, on purpose.
* RLlib's "RLModule(config=[RLModuleConfig object]) has been deprecated": RLlib 2.60's own
  `RLModule.__init__` builds an `RLModuleConfig` for backward compatibility, so every module
  triggers it, ours included although they use the new constructor arguments.
* gymnasium's "Overriding environment rllib-... already in registry": RLlib's env runners
  register their vector-env wrapper id each time they build one.
* Tune's "Install gputil for GPU system monitoring." (utilisation stats only), its
  TensorBoard logger dropping tuple-valued hyperparameters (the MLflow params keep them),
  and "Trainable.setup took N s ... consider setting reuse_actors=True" (the grid does; the
  time is RLlib building the algorithm).
* Tune's "Resume experiment with: Tuner.restore(...)" after an interrupt: the driver prints the
  grid's own resume command (`tune GRID.yaml --resume`), which also continues the MLflow runs and
  the baselines; Tuner.restore alone would not.

Installed in the driver, in every trial (`UavLoraTrainable.setup`) and, through Ray's
``worker_process_setup_hook``, in every other worker process of the job (env runners).
"""

from __future__ import annotations

import logging
import warnings

# (logger name, message fragment)
_LOG_MESSAGES = (
    ("ray.rllib.algorithms.algorithm_config", "on the new API stack!"),
    ("ray._common.deprecation", "RLModule(config=[RLModuleConfig"),
    ("ray.tune.utils.util", "Install gputil for GPU system monitoring"),
    ("ray.tune.logger.tensorboardx", "Removed the following hyperparameter values"),
    ("ray.tune.trainable.trainable", "consider setting reuse_actors=True"),
    ("ray.tune.tune", "Resume experiment with: Tuner.restore"),
)


class _DropFragment(logging.Filter):
    def __init__(self, fragment: str):
        super().__init__()
        self.fragment = fragment

    def filter(self, record: logging.LogRecord) -> bool:
        return self.fragment not in record.getMessage()


def quiet_known_warnings() -> None:
    """Idempotent: install the filters once per process."""
    for name, fragment in _LOG_MESSAGES:
        logger = logging.getLogger(name)
        if not any(isinstance(f, _DropFragment) and f.fragment == fragment for f in logger.filters):
            logger.addFilter(_DropFragment(fragment))
    warnings.filterwarnings("ignore", message=r".*Overriding environment rllib-\S+ already in registry")


SETUP_HOOK = f"{__name__}.quiet_known_warnings"  # for ray.init(runtime_env={"worker_process_setup_hook": ...})
