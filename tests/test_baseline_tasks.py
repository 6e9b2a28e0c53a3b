"""How the driver reports a baseline evaluation that failed (experiment/baseline_tasks.py)."""

from __future__ import annotations

from ray.exceptions import RayTaskError

from uavlora_rllib.experiment.baseline_tasks import failure_text


def test_a_failed_evaluation_is_reported_by_what_it_raised():
    """str() of a RayTaskError starts with the remote traceback: 300 characters of it named no error."""
    try:
        raise ValueError("unknown baseline 'min_power'")
    except ValueError as exc:
        remote = RayTaskError("evaluate_baseline", "Traceback (most recent call last):\n" + "  File x\n" * 50, exc)
    assert failure_text(remote) == "ValueError: unknown baseline 'min_power'"
    assert failure_text(RuntimeError("node died\n  4 times")) == "RuntimeError: node died 4 times"
    assert len(failure_text(ValueError("x" * 1000))) == 300
