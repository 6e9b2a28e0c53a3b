"""The report's learning verdicts (analysis.verdicts) on hand-made run records and curves."""

from __future__ import annotations

import math

import pytest

from analysis.data import organise
from analysis.runs import EE_KEY
from analysis.verdicts import (
    SWING_LIMIT,
    last_evals_spread,
    learning_md,
    learning_table,
    share_target,
    stopped_before_budget,
)
from tests.conftest import finished_record


def _run(i, alg, ee, kind="train", seed="0", scen=(10, 2)):
    params = {"scenario.action_mode": "per_device", "stop.env_steps": "200000"}
    return finished_record(i, alg, kind=kind, seed=seed, scen=scen, params=params, metrics={EE_KEY: ee})


CURVES = {
    "r2": [50.0, 90.0, 95.0, 94.0, 96.0],  # settled: spread 2/96
    "r3": [50.0, 99.0, 80.0, 97.0, 98.0],  # swings: spread 18/98
    "r4": [60.0, 70.0, 72.0],
    "r5": [10.0, 20.0],  # too few evaluations
}


STOPPED = {"r4": 100_000}  # a run a scheduler stopped at half its budget: its last evaluation's env steps


def _history(record, key):
    """Evaluations spread evenly up to the run's budget (200k), or to where it was stopped."""
    assert key == EE_KEY
    vals = CURVES[record.run_id]
    end = STOPPED.get(record.run_id, 200_000)
    return [end * (i + 1) / len(vals) for i in range(len(vals))], vals


def test_last_evals_spread():
    assert last_evals_spread([1.0, 100.0, 95.0, 100.0]) == pytest.approx(0.05)
    assert math.isnan(last_evals_spread([1.0, 2.0]))
    assert math.isnan(last_evals_spread([0.0, 0.0, 0.0]))


def test_learning_rows_shares_best_fixed_and_swings():
    runs = [
        _run(0, "greedy", 100.0, kind="baseline"),
        _run(1, "best_fixed", 80.0, kind="baseline"),
        _run(10, "greedy", 100.0, kind="baseline", seed="1"),
        _run(11, "best_fixed", 80.0, kind="baseline", seed="1"),
        _run(2, "mappo", 95.0, seed="0"),
        _run(3, "mappo", 97.0, seed="1"),
        _run(4, "ippo", 72.0),
        _run(5, "coma", 85.0, scen=(60, 4)),  # no reference in that scenario: no row
    ]
    rows = {r["algorithm"]: r for r in learning_table(organise(runs), _history)}
    assert set(rows) == {"mappo", "ippo"}
    m = rows["mappo"]
    assert m["share_of_reference"] == pytest.approx(0.96) and m["n_seeds"] == 2
    assert m["share_of_best_fixed"] == pytest.approx(96 / 80) and m["above_best_fixed"] == "true"
    assert m["max_last_evals_spread"] == pytest.approx(18 / 98)  # the worse seed counts
    assert m["settled"] == "false" and m["env_steps"] == "200000" and m["trained_env_steps"] == "200000"
    assert m["share_target"] == 0.9 and m["meets_share_target"] == ""  # 2 seeds: not judged
    i = rows["ippo"]
    assert i["above_best_fixed"] == "false"
    assert i["max_last_evals_spread"] == pytest.approx(12 / 72) and i["settled"] == str(12 / 72 <= SWING_LIMIT).lower()
    md = learning_md(list(rows.values()))
    assert (
        "| 10 | 2 | per_device | mappo | 2 | 200000 (200000) | 0.960 | 0.800 | 1.200 | true | 0.184 | false | 0.90 | n/a (needs 3 seeds"
        in md
    )


def test_a_run_stopped_before_its_budget_is_shown_noted_and_not_judged():
    runs = [_run(10 + k, "greedy", 100.0, kind="baseline", seed=str(k)) for k in range(3)] + [
        _run(2 + k, "mappo", v, seed=str(k)) for k, v in enumerate((95.0, 97.0, 93.0))
    ]
    org = organise(runs)
    (row,) = learning_table(org, _history)
    assert row["trained_env_steps"] == "100000/200000" and row["meets_share_target"] == ""
    assert "| 100000/200000 (200000) |" in learning_md([row])
    assert stopped_before_budget(org, _history) == [
        "V=10 U=2 mappo: 1 of 3 run(s) stopped before the budget 200000 (seed 2 at 100000 env steps; a scheduler's "
        "early stop): their EE is of a shorter training"
    ]


def test_share_target_is_judged_on_three_seeds_at_the_budget(monkeypatch):
    monkeypatch.delitem(STOPPED, "r4")  # every run trained its budget
    runs = [_run(10 + k, "greedy", 100.0, kind="baseline", seed=str(k)) for k in range(3)] + [
        _run(2 + k, "mappo", v, seed=str(k)) for k, v in enumerate((95.0, 97.0, 72.0))
    ]

    (row,) = learning_table(organise(runs), _history)
    assert row["n_seeds"] == 3 and row["share_of_reference"] == pytest.approx(88 / 100)
    assert row["meets_share_target"] == "false"  # 0.88 < 0.9


def test_share_targets_by_mode_and_uavs():
    assert share_target("per_device", 8) == 0.9
    assert [share_target("per_uav", u) for u in (2, 4, 8)] == [0.95, 0.85, 0.75]


def test_a_seed_without_enough_evaluations_leaves_settled_open():
    runs = [_run(0, "greedy", 100.0, kind="baseline"), _run(5, "vdn", 50.0)]
    (row,) = learning_table(organise(runs), _history)
    assert row["settled"] == "" and math.isnan(row["max_last_evals_spread"]) and row["above_best_fixed"] == ""
    assert "n/a (too few evaluations)" in learning_md([row])


def test_ratios_compare_matched_seeds_only():
    """Each seed has its own evaluation episodes: a learner missing a seed (or a baseline missing
    one) is compared on the seeds both ran, never a 2-seed mean over a 3-seed mean (issue 23)."""
    runs = [
        *[_run(k, "greedy", 100.0, kind="baseline", seed=str(k)) for k in range(3)],
        *[_run(10 + k, "best_fixed", v, kind="baseline", seed=str(k)) for k, v in enumerate((90.0, 90.0, 30.0))],
        _run(20, "coma", 90.0, seed="0"),
        _run(21, "coma", 90.0, seed="1"),
        _run(22, "ippo", 72.0, seed="0"),
        _run(23, "ippo", 72.0, seed="5"),  # no reference for seed 5
    ]
    rows = {r["algorithm"]: r for r in learning_table(organise(runs), lambda r, k: ([], []))}
    c = rows["coma"]
    assert c["share_of_best_fixed"] == pytest.approx(1.0)  # not 90 / 70 over all best_fixed seeds
    assert c["best_fixed_share_of_reference"] == pytest.approx(0.9) and c["above_best_fixed"] == "false"
    assert c["n_seeds"] == 2 and c["unmatched_seeds"] == ""
    i = rows["ippo"]
    assert i["n_seeds"] == 1 and i["unmatched_seeds"] == "5"
    assert i["share_of_reference"] == pytest.approx(0.72)
    assert "| ippo | 1 (left out: 5) |" in learning_md([i])


def test_the_report_reads_each_metric_history_once():
    """The learning table, the early-stop notes and Fig. 3a all read a run's execution curve: the
    report's history asks the tracking store once per (run, metric)."""
    from types import SimpleNamespace

    from analysis.data import mlflow_history

    calls = []

    def get_metric_history(run_id, key):
        calls.append((run_id, key))
        return [SimpleNamespace(step=s, timestamp=s, value=float(s)) for s in (0, 10)]

    history = mlflow_history([SimpleNamespace(client=SimpleNamespace(get_metric_history=get_metric_history))])
    record = _run(2, "mappo", 95.0)
    assert history(record, EE_KEY) == history(record, EE_KEY) == ([0.0, 10.0], [0.0, 10.0])
    history(record, "episode_return_mean")
    assert calls == [("r2", EE_KEY), ("r2", "episode_return_mean")]


def test_curves_take_the_tables_run_of_each_seed():
    """Two finished runs of one seed: the tables use the newest, and so does the execution curve (a
    curve of 3 runs over 2 seeds would weigh one seed twice)."""
    from analysis.data import curves

    runs = [_run(30, "mappo", 10.0, seed="0"), _run(31, "mappo", 20.0, seed="1"), _run(32, "mappo", 40.0, seed="0")]
    ends = {"r30": 10.0, "r31": 20.0, "r32": 40.0}
    org = organise(runs)
    assert org.cells[(10, 2, "mappo")].seeds == ["0", "1"]
    out, _ = curves(lambda r, k: ([0.0, 200_000.0], [0.0, ends[r.run_id]]), org, EE_KEY, smooth=0.0, points=3)
    curve = out[(10, 2)]["mappo"]
    assert sorted(curve.seeds) == ["0", "1"] and curve.mean[-1] == pytest.approx(30.0)  # (40 + 20) / 2


def test_a_learner_of_another_scenario_gets_no_share_of_the_reference():
    """Joined experiments: a learner trained with another rate model at the same V, U is not divided by
    this scenario's reference (a share of 5x greedy was shown); a run that did not log a param matches."""
    lora = {"scenario.rate_model": "lora_phy"}
    runs = [
        *[_run(k, "greedy", 100.0, kind="baseline", seed=str(k)) for k in range(3)],
        *[finished_record(10 + k, "mappo", seed=str(k), params=lora, metrics={EE_KEY: 500.0}) for k in range(3)],
        *[_run(20 + k, "ippo", 90.0, seed=str(k)) for k in range(3)],
    ]
    for r in runs[:3]:
        r.params["scenario.rate_model"] = "shannon"
    org = organise(runs)
    assert org.matched_seeds(org.cells[(10, 2, "mappo")]) == []
    assert org.matched_seeds(org.cells[(10, 2, "ippo")]) == ["0", "1", "2"]  # it logged no rate model
    rows = {r["algorithm"]: r for r in learning_table(org, lambda r, k: ([], []))}
    assert "mappo" not in rows and rows["ippo"]["share_of_reference"] == pytest.approx(0.9)  # no share to judge
    assert org.normalised(org.cells[(10, 2, "mappo")]).size == 0
    assert any("mappo (train): seed(s) 0, 1, 2 have no greedy run" in w for w in org.warnings), org.warnings
    from analysis.data import curves

    drawn, notes = curves(lambda r, k: ([0.0, 1.0], [1.0, 2.0]), org, EE_KEY, 0.0, 3, matched=True)
    assert set(drawn[(10, 2)]) == {"greedy", "ippo"} or set(drawn[(10, 2)]) == {"ippo"}  # Fig. 3a: not mappo
    assert any("mappo: seed(s) 0, 1, 2 left out" in n and "on the same task" in n for n in notes), notes
