"""The paper side by side (analysis.paper) judges only runs of the paper's scenario: the paper's
numbers are of per_uav mode, the Shannon rate and its reward, so runs of another scenario at the
same (V, U) get "not comparable", naming the settings, and keep their numbers."""

from __future__ import annotations

import pytest

from analysis.data import organise
from analysis.paper import paper_rows, paper_scenario_params
from analysis.runs import EE_KEY
from tests.conftest import finished_record


def _run(i, alg, seed, ee, params):
    return finished_record(i, alg, seed=str(seed), params=params, metrics={EE_KEY: ee})


def _rows(params):
    runs = [
        _run(10 * s + k, alg, s, ee + s, params)
        for s in range(3)
        for k, (alg, ee) in enumerate((("mappo", 136.0), ("vdn", 100.0), ("qmix", 50.0)))
    ]
    return {(r["n_eds"], r["other"]): r for r in paper_rows(organise(runs))}


def test_the_papers_scenario_is_judged():
    rows = _rows(paper_scenario_params(10))
    assert rows[(10, "vdn")]["verdict"] == "inside our CI"
    assert rows[(10, "qmix")]["verdict"].startswith("agrees")


def test_another_scenario_is_not_comparable():
    params = {**paper_scenario_params(10), "scenario.action_mode": "per_device", "scenario.rate_model": "lora_phy"}
    rows = _rows(params)
    for other in ("vdn", "qmix"):
        r = rows[(10, other)]
        assert r["verdict"] == (
            "not comparable: not the paper's scenario (scenario.action_mode per_device, scenario.rate_model lora_phy)"
        )
    assert rows[(10, "vdn")]["ours_point"] == pytest.approx(100 * (137.0 / 101.0 - 1))  # still shown


def test_another_scenario_is_named_before_the_seed_count():
    """One seed of a non-paper scenario: "too few seeds" would hide that the numbers are not the paper's."""
    params = {**paper_scenario_params(10), "scenario.episode_len": "50"}
    runs = [_run(k, alg, 0, ee, params) for k, (alg, ee) in enumerate((("mappo", 136.0), ("vdn", 100.0)))]
    rows = {(r["n_eds"], r["other"]): r for r in paper_rows(organise(runs))}
    assert rows[(10, "vdn")]["verdict"] == "not comparable: not the paper's scenario (scenario.episode_len 50)"
    assert rows[(10, "qmix")]["verdict"] == "not run"


def test_params_an_older_run_did_not_log_are_not_counted():
    rows = _rows({"scenario.n_eds": "10", "scenario.n_uavs": "2"})
    assert rows[(10, "vdn")]["verdict"] == "inside our CI"


def test_an_unset_w1_is_the_default_it_applied():
    """A run that left reward.w1 null (logged "None") and one that set the rate model's default are
    one scenario: the paper's own w1 set explicitly is still the paper's scenario."""
    from analysis.runs import resolved_params

    assert resolved_params({"scenario.reward.w1": "None"})["scenario.reward.w1"] == "0.0004"
    lora = {"scenario.reward.w1": "None", "scenario.rate_model": "lora_phy"}
    assert resolved_params(lora)["scenario.reward.w1"] == "0.1"
    rows = _rows({**paper_scenario_params(10), "scenario.reward.w1": "0.0004"})
    assert rows[(10, "vdn")]["verdict"] == "inside our CI"
