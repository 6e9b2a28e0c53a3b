"""The known harmless library messages are filtered; others from the same loggers still show."""

from __future__ import annotations

import logging
import warnings

from uavlora_rllib.experiment.quiet import quiet_known_warnings


def test_known_messages_are_dropped_and_others_kept(caplog):
    quiet_known_warnings()
    quiet_known_warnings()  # idempotent: one filter per message
    cfg_logger = logging.getLogger("ray.rllib.algorithms.algorithm_config")
    assert len(cfg_logger.filters) == len({id(f) for f in cfg_logger.filters}) == 1
    with caplog.at_level(logging.INFO):
        cfg_logger.warning("You are running MAPPO on the new API stack! This is the new default ...")
        logging.getLogger("ray._common.deprecation").warning(
            "DeprecationWarning: `RLModule(config=[RLModuleConfig object])` has been deprecated."
        )
        logging.getLogger("ray.tune.trainable.trainable").info(
            "Trainable.setup took 15.2 seconds. If your trainable is slow to initialize, consider setting "
            "reuse_actors=True to reduce actor creation overheads."
        )
        logging.getLogger("ray.tune.tune").warning(
            "Experiment has been interrupted, but the most recent state was saved.\n"
            'Resume experiment with: Tuner.restore(path="/x/smoke", trainable=...)'
        )
        cfg_logger.warning("Some other config problem")
        logging.getLogger("ray._common.deprecation").warning("DeprecationWarning: `foo` has been deprecated.")
    assert [r.getMessage() for r in caplog.records] == [
        "Some other config problem",
        "DeprecationWarning: `foo` has been deprecated.",
    ]
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        quiet_known_warnings()  # catch_warnings reset the filters
        warnings.warn(
            "\x1b[33mWARN: Overriding environment rllib-multi-agent-env-v0 already in registry.\x1b[0m", stacklevel=1
        )
        warnings.warn("Overriding environment MyEnv-v0 already in registry.", stacklevel=1)
    assert [str(w.message) for w in seen] == ["Overriding environment MyEnv-v0 already in registry."]
