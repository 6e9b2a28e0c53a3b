"""The report's open-loop check and its reference in either action mode, on hand-made run records."""

from __future__ import annotations

import math

import pytest

from analysis.data import BOUND_KEY, organise
from analysis.runs import EE_KEY
from analysis.tables import OPEN_LOOP_SHARE, open_loop_md, open_loop_table
from tests.conftest import finished_record


def _run(i, alg, scen, ee, mode, bound=None, seed="0"):
    metrics = {EE_KEY: ee} | ({BOUND_KEY: bound} if bound is not None else {})
    params = {"scenario.action_mode": mode}
    return finished_record(i, alg, kind="baseline", seed=seed, scen=scen, params=params, metrics=metrics)


def test_open_loop_rows_shares_modes_and_bracket():
    runs = [
        _run(0, "optimal", (10, 2), 200.0, "per_uav", bound=250.0),
        _run(1, "greedy", (10, 2), 190.0, "per_uav", bound=250.0),
        _run(2, "best_fixed", (10, 2), 199.0, "per_uav"),  # 0.995: a constant is optimal
        _run(3, "greedy", (60, 4), 240.0, "per_device", bound=300.0),
        _run(4, "best_fixed", (60, 4), 120.0, "per_device"),  # 0.5
        _run(5, "greedy", (60, 8), 100.0, "per_device"),  # no best_fixed run, no bound logged
    ]
    org = organise(runs)
    ref = org.reference((60, 4))
    assert (ref.name, ref.mode, ref.bound) == ("greedy", "per_device", 300.0)
    assert ref.label == "greedy baseline (per_device)"
    assert org.reference((10, 2)).label == "per-slot optimum (per_uav)"  # optimal wins over greedy
    rows = {(r["n_eds"], r["n_uavs"]): r for r in open_loop_table(org)}
    assert rows[(10, 2)]["best_fixed_share_of_reference"] == pytest.approx(199.0 / 200.0)
    assert rows[(10, 2)]["constant_is_optimal"] == "true"
    assert rows[(10, 2)]["reference_share_of_bound"] == pytest.approx(200.0 / 250.0)
    assert rows[(60, 4)]["constant_is_optimal"] == "false" and rows[(60, 4)]["action_mode"] == "per_device"
    assert math.isnan(rows[(60, 8)]["best_fixed_share_of_reference"]) and rows[(60, 8)]["constant_is_optimal"] == ""
    md = open_loop_md(list(rows.values()))
    assert "V=10 U=2 (per_uav): a constant action is optimal here" in md and "cannot be told apart" in md
    assert "V=60 U=4 (per_device): best_fixed reaches 0.500" in md
    assert "V=60 U=8 (per_device): no best_fixed run" in md
    assert OPEN_LOOP_SHARE == 0.98


def test_open_loop_share_and_normalised_scores_use_matched_seeds():
    runs = [
        _run(0, "greedy", (60, 4), 100.0, "per_device", seed="0"),
        _run(1, "greedy", (60, 4), 300.0, "per_device", seed="1"),
        _run(2, "best_fixed", (60, 4), 50.0, "per_device", seed="0"),  # seed 0 only
    ]
    org = organise(runs)
    (row,) = open_loop_table(org)
    assert row["best_fixed_share_of_reference"] == pytest.approx(0.5)  # not 50 / 200
    assert org.reference((60, 4)).mean == pytest.approx(200.0)  # without seeds: all of them
    assert org.normalised(org.cells[(60, 4, "best_fixed")]) == pytest.approx([0.5])
