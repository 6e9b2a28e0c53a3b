"""The report across experiments and tracking stores, on two synthetic sqlite stores with known numbers.

Store A, experiment sweep_V10 (V=10, U=2): mappo seeds 0/1/2 -> EE 100/110/120, ippo 0.1 below
mappo on every seed (overlapping series), vdn 80/85/90, qmix 40/50/60, baseline greedy 150 (no
optimal baseline: the reference is greedy).
Store B, experiment sweep_V20 (V=20, U=2): mappo seed 0 -> 50, ippo 49.9, vdn 40 (one seed each),
baseline greedy 140; experiment unrelated (not matched by the glob sweep_*).
Every learner run logs the periodic greedy evaluation (eval/ee_sys_mean, eval/ee_sys_episode_sum,
eval/success_rate, eval/episode_return) at env steps 0 and 5000 = EE * 0.5 / EE * 0.75, and the
final evaluation at 10000 = EE; vdn at V=20 lacks the 5000 point.
"""

from __future__ import annotations

import csv
import json
import subprocess
import sys
import time

import numpy as np
import pytest
from conftest import finished_record
from scipy import stats as st

mlflow = pytest.importorskip("mlflow")
from mlflow.entities import Metric, Param  # noqa: E402
from mlflow.tracking import MlflowClient  # noqa: E402

from analysis import report  # noqa: E402
from analysis.paper import PAPER_VDN_IMPROVEMENT_PCT  # noqa: E402

ROOT = __file__.rsplit("/tests/", 1)[0]
EE_A = {
    "mappo": [100.0, 110.0, 120.0],
    "ippo": [99.9, 109.9, 119.9],
    "vdn": [80.0, 85.0, 90.0],
    "qmix": [40.0, 50.0, 60.0],
}
EE_B = {"mappo": [50.0], "ippo": [49.9], "vdn": [40.0]}
STEPS = {0: 0.5, 5000: 0.75}
FINAL = 10_000


def _run(client, exp_id, kind, alg, v, seed, ee, skip_steps=()):
    tags = {
        "kind": kind,
        "algorithm": alg,
        "seed": str(seed),
        "n_eds": str(v),
        "n_uavs": "2",
        "git_commit": "abc",
        "grid_file": "g.yaml",
        "budget_env_steps": str(FINAL),
    }
    run = client.create_run(exp_id, run_name=f"{alg}-V{v}-s{seed}", tags=tags)
    now = int(time.time() * 1000)
    final = FINAL if kind == "train" else 0
    keys = {
        "eval/ee_sys_mean": 1.0,
        "eval/ee_sys_episode_sum": 150.0,
        "eval/success_rate": 0.01,
        "eval/episode_return": 0.1,
    }
    metrics = [Metric(k, ee * f, now, final) for k, f in keys.items()]
    if kind == "train":
        metrics += [
            Metric(k, ee * f * frac, now, s)
            for s, frac in STEPS.items()
            if s not in skip_steps
            for k, f in keys.items()
        ]
        metrics += [Metric("episode_return_mean", 1.0 + s / 1000, now, s) for s in range(0, FINAL + 1, 2500)]
    params = [Param("scenario.n_eds", str(v)), Param("scenario.n_uavs", "2"), Param("eval.episodes", "10")]
    if kind == "train":
        params.append(Param("stop.env_steps", str(FINAL)))
    client.log_batch(run.info.run_id, metrics=metrics, params=params)
    client.set_terminated(run.info.run_id, "FINISHED")


@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("join")
    uri_a, uri_b = f"sqlite:///{tmp / 'a.db'}", f"sqlite:///{tmp / 'b.db'}"
    ca, cb = MlflowClient(tracking_uri=uri_a), MlflowClient(tracking_uri=uri_b)
    ea = ca.create_experiment("sweep_V10", artifact_location=str(tmp / "art_a"))
    eb = cb.create_experiment("sweep_V20", artifact_location=str(tmp / "art_b"))
    eu = cb.create_experiment("unrelated", artifact_location=str(tmp / "art_u"))
    for alg, values in EE_A.items():
        for seed, ee in enumerate(values):
            _run(ca, ea, "train", alg, 10, seed, ee)
    for seed in range(3):
        _run(ca, ea, "baseline", "greedy", 10, seed, 150.0)
    for alg, values in EE_B.items():
        _run(cb, eb, "train", alg, 20, 0, values[0], skip_steps=(5000,) if alg == "vdn" else ())
    _run(cb, eb, "baseline", "greedy", 20, 0, 140.0)
    _run(cb, eu, "train", "mappo", 40, 0, 1.0)  # must not be joined
    out = tmp / "report"
    rc = report.main(
        [
            "--experiment",
            "sweep_*",
            "--tracking-uri",
            uri_a,
            "--tracking-uri",
            uri_b,
            "--out",
            str(out),
            "--points",
            "11",
        ]
    )
    assert rc == 0
    return {"a": uri_a, "b": uri_b, "out": out, "tmp": tmp, "clients": (ca, cb)}


def _rows(path):
    with open(path) as fh:
        return list(csv.DictReader(fh))


def test_join_across_experiments_and_uris(stores):
    rows = _rows(stores["out"] / "table_ee.csv")
    assert {(r["n_eds"], r["algorithm"]) for r in rows} == {("10", a) for a in (*EE_A, "greedy")} | {
        ("20", a) for a in (*EE_B, "greedy")
    }  # V=40 (unrelated) absent
    text = (stores["out"] / "report.md").read_text()
    assert "`sweep_V10`" in text and "`sweep_V20`" in text and "unrelated" not in text
    assert (stores["out"] / "fig3b.png").is_file()  # V=10 and V=20 come from different stores
    assert "not logged to MLflow" in text
    for client in stores["clients"]:  # nothing written into either store
        for exp in client.search_experiments():
            assert not [r for r in client.search_runs([exp.experiment_id]) if r.data.tags.get("kind") == "summary"]


def test_missing_optimum_uses_greedy_reference(stores):
    rows = {(r["n_eds"], r["algorithm"]): r for r in _rows(stores["out"] / "table_ee.csv")}
    assert rows[("10", "mappo")]["reference_baseline"] == "greedy"
    assert float(rows[("10", "mappo")]["share_of_reference"]) == pytest.approx(110.0 / 150.0)
    assert float(rows[("20", "vdn")]["share_of_reference"]) == pytest.approx(40.0 / 140.0)
    md = (stores["out"] / "table_ee.md").read_text()
    assert "0.733 of greedy" in md
    curves = [r for r in _rows(stores["out"] / "fig3a_curves.csv") if r["metric"] == "eval/ee_sys_mean"]
    assert curves and {r["reference"] for r in curves} == {"greedy"}
    assert "share of the greedy baseline" in (stores["out"] / "report.md").read_text()


def test_coincident_series_named_and_titles_state_n(stores):
    text = (stores["out"] / "report.md").read_text()
    notes = [ln for ln in text.splitlines() if "overlap at every point" in ln]
    assert any(ln.startswith("- Fig. 3b") and "ippo and mappo" in ln for ln in notes), notes
    assert any(ln.startswith("- Fig. 3a (a)") and "ippo and mappo" in ln for ln in notes), notes
    exec_notes = [ln for ln in notes if ln.startswith(("- Fig. 3b", "- Fig. 3a (a)"))]
    assert not any("qmix" in ln for ln in exec_notes)  # qmix's EE is far from the rest
    # every learner logs the same training return here: panel (b) names every pair
    ret = next(ln for ln in notes if ln.startswith("- Fig. 3a (b)"))
    assert all(f"{a} and {b}" in ret for a, b in (("ippo", "mappo"), ("mappo", "qmix"), ("qmix", "vdn")))
    svg = (stores["out"] / "fig3b.svg").read_text()
    # V=10 cells have 3 seeds, V=20 cells 1: the title says so, and that bars exist only for n >= 2
    assert "n=1-3 seeds; 95% t CI bars where n&gt;=2" in svg or "n=1-3 seeds; 95% t CI bars where n>=2" in svg
    assert "95% t CI)" not in svg
    caption = text.split("### Fig. 3b")[1].split("###")[0]  # the caption in report.md says it too
    assert "U=2; mean over n=1-3 seeds; 95% t CI bars where n>=2" in caption
    from analysis.figures import interval_text, looks

    assert interval_text([1, 1], "95% t CI") == "n=1 seed: no interval"
    lk = looks(["mappo", "ippo", "vdn", "qmix"])
    assert len({(v["marker"], str(v["linestyle"])) for v in lk.values()}) == 4
    assert len({str(v["linestyle"]) for v in lk.values()}) == 4 and len({v["marker"] for v in lk.values()}) == 4


def _fieller(a, b):
    """Brute force: every rho on a fine grid with (ma - rho mb)^2 <= t^2 (va + rho^2 vb)."""
    a, b = np.asarray(a), np.asarray(b)
    t = st.t.ppf(0.975, min(a.size, b.size) - 1)
    rho = np.linspace(0.0, 10.0, 2_000_001)
    ok = rho[(a.mean() - rho * b.mean()) ** 2 <= t * t * (a.var(ddof=1) / a.size + rho**2 * b.var(ddof=1) / b.size)]
    return ok.min(), ok.max()


def test_paper_table(stores):
    rows = {(int(r["n_eds"]), r["other"]): r for r in _rows(stores["out"] / "table_paper.csv")}
    assert {v for v, _ in rows} == set(PAPER_VDN_IMPROVEMENT_PCT)
    r = rows[(10, "vdn")]
    assert float(r["ours_point"]) == pytest.approx(100 * (110 / 85 - 1))
    lo, hi = _fieller(EE_A["mappo"], EE_A["vdn"])
    assert float(r["ours_ci95_low"]) == pytest.approx(100 * (lo - 1), abs=1e-3)
    assert float(r["ours_ci95_high"]) == pytest.approx(100 * (hi - 1), abs=1e-3)
    assert r["paper_claim"] == "+36.02%" and r["n_seeds_mappo"] == "3" and r["n_seeds_other"] == "3"
    assert r["verdict"] == "inside our CI"  # 36.02 lies in [-3.1, 67.5]
    q = rows[(10, "qmix")]
    assert float(q["ours_point"]) == pytest.approx(110 / 50)
    qlo, qhi = _fieller(EE_A["mappo"], EE_A["qmix"])
    assert float(q["ours_ci95_low"]) == pytest.approx(qlo, abs=1e-5)
    assert q["verdict"] == ("agrees (our CI above 2x)" if qlo > 2 else "undecided (our CI contains 2x)")
    assert rows[(20, "vdn")]["verdict"].startswith("too few seeds")
    assert float(rows[(20, "vdn")]["ours_point"]) == pytest.approx(25.0)  # the point estimate is still shown
    assert rows[(60, "vdn")]["verdict"] == "not run" and rows[(20, "qmix")]["verdict"] == "not run"
    md = (stores["out"] / "table_paper.md").read_text()
    assert "+39.01%" in md and "above 2x at 1 of 1 V value(s)" in md


def test_marl_eval_export(stores):
    """The raw-data structure marl-eval's loader reads (its README and data_process_pipeline):
    env -> task -> algorithm -> run -> step_i {step_count:int, metric: [numbers]}, absolute_metrics
    the LAST key of each run, the same metrics everywhere, equal step counts in every run."""
    data = json.loads((stores["out"] / "results_marl_eval.json").read_text())
    assert list(data) == ["uavlora"]
    env = data["uavlora"]
    assert set(env) == {"v10_u2", "v20_u2"}
    assert set(env["v10_u2"]) == set(EE_A) and set(env["v20_u2"]) == set(EE_B)
    assert set(env["v10_u2"]["mappo"]) == {"seed_0", "seed_1", "seed_2"}
    metric_names = {"ee_sys_mean", "ee_sys_episode_sum", "success_rate", "return"}
    n_keys = set()
    for task in env.values():
        for runs in task.values():
            for run in runs.values():
                keys = list(run)
                assert keys[-1] == "absolute_metrics"
                n_keys.add(len(keys))
                counts = []
                for k in keys[:-1]:
                    assert k == f"step_{keys.index(k)}"
                    assert isinstance(run[k]["step_count"], int)
                    counts.append(run[k]["step_count"])
                    assert set(run[k]) - {"step_count"} == metric_names
                    assert all(isinstance(x, float) for m in metric_names for x in run[k][m])
                assert counts == sorted(counts)
                assert set(run["absolute_metrics"]) == metric_names
    # vdn at V=20 has no evaluation at 5000: every run keeps the places of the schedule all have, 0 and the
    # final 10000, so that step_1 is the same point of training in every run (+ absolute_metrics)
    assert n_keys == {3}
    run = env["v10_u2"]["mappo"]["seed_1"]
    assert run["step_0"]["step_count"] == 0 and run["step_0"]["ee_sys_mean"] == [55.0]
    assert run["step_1"]["step_count"] == 10000 and run["step_1"]["ee_sys_mean"] == [110.0]
    assert env["v20_u2"]["vdn"]["seed_0"]["step_1"]["step_count"] == 10000
    assert run["absolute_metrics"]["ee_sys_mean"] == [110.0]
    assert run["absolute_metrics"]["return"] == [pytest.approx(11.0)]
    text = (stores["out"] / "report.md").read_text()
    assert "each keeps the 2 places every run has" in text
    assert "different numbers of runs" in text  # 3 seeds at V=10, 1 at V=20


def test_marl_eval_places_on_the_evaluation_schedule():
    """Evaluations every 20k over a 200k budget land at the first iteration past each multiple; a restored
    trial's extra evaluation (26,400) is not a place of its own, and a run stopped at 170k has places 1-8."""
    from analysis.export import schedule_interval, schedule_places

    full = [20400.0, 26400.0, 40800.0, 60000.0, 80400.0, 100800.0, 120000.0, 140400.0, 160800.0, 180000.0, 200400.0]
    early = [20400.0, 40800.0, 60000.0, 80400.0, 100800.0, 120000.0, 140400.0, 160800.0, 170400.0]
    gaps = np.diff(full).tolist() + np.diff(early).tolist()
    interval = schedule_interval(gaps, 200000.0)
    assert interval == 20000.0
    places = schedule_places(full, interval)
    assert sorted(places) == list(range(1, 11)) and places[1] == 20400.0 and 26400.0 not in places.values()
    assert sorted(schedule_places(early, interval)) == list(range(1, 9))
    assert schedule_interval([], 200000.0) is None and schedule_interval([5000.0], None) == 5000.0
    # an interval that does not divide the budget: the logged one places runs of other iteration sizes alike
    mappo, qmix = [15000.0, 30000.0, 45000.0, 60000.0], [16000.0, 30000.0, 46000.0, 60000.0]
    interval = schedule_interval(np.diff(mappo).tolist() + np.diff(qmix).tolist(), 200000.0, logged=15000.0)
    assert sorted(schedule_places(mappo, interval)) == sorted(schedule_places(qmix, interval)) == [1, 2, 3, 4]


def test_fig2_best_learner_or_flag(stores):
    text = (stores["out"] / "report.md").read_text()
    fig2 = text.split("### Fig. 2")[1].split("###")[0]
    assert "mappo at V=10, U=2, the learner with the highest seed-mean execution EE" in fig2
    out = stores["tmp"] / "flag"
    assert (
        report.main(
            [
                "--experiment",
                "sweep_V10",
                "--tracking-uri",
                stores["a"],
                "--out",
                str(out),
                "--fig2-algorithm",
                "VDN",
                "--no-log",
                "--points",
                "5",
            ]
        )
        == 0
    )
    fig2 = (out / "report.md").read_text().split("### Fig. 2")[1].split("###")[0]
    assert "vdn at V=10, U=2, chosen with --fig2-algorithm" in fig2


def test_logging_failure_is_one_line(stores, tmp_path, capsys, monkeypatch):
    from mlflow.exceptions import MlflowException

    def fail(*a, **k):
        raise MlflowException("attempt to write a readonly database\nmore detail")

    monkeypatch.setattr(report, "log_summary", fail)
    out = tmp_path / "r"
    assert (
        report.main(
            [
                "--experiment",
                "sweep_V10",
                "--tracking-uri",
                stores["a"],
                "--out",
                str(out),
                "--no-fig2",
                "--points",
                "5",
            ]
        )
        == 2
    )
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "readonly database" in err and "--no-log" in err
    assert (out / "report.md").is_file()  # the files were written before logging failed


def test_error_paths_one_line_exit_2(stores, tmp_path, capsys):
    a = stores["a"]
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    cases = [
        (["--experiment", "sweep_V10", "--tracking-uri", a, "--out", str(a_file)], "is a file"),
        (["--experiment", "sweep_V10", "--tracking-uri", a, "--out", str(a_file / "sub")], "--out"),
        (
            [
                "--experiment",
                "sweep_V10",
                "--tracking-uri",
                a,
                "--out",
                str(tmp_path / "o"),
                "--fig2-algorithm",
                "nope",
            ],
            "--fig2-algorithm: 'nope' has no training runs",
        ),
        (["--experiment", "nothing_*", "--tracking-uri", a], "'nothing_*' not found"),
        (
            ["--experiment", "sweep_V10", "--tracking-uri", a, "--fig2-seed", "-1"],
            "--fig2-seed: must be an integer in [0, 4294967295], got -1",
        ),
        (["--experiment", "sweep_V10", "--tracking-uri", a, "--smooth", "2"], "[0, 1)"),
        (["--tracking-uri", a], "--experiment"),
    ]
    for argv, needle in cases:
        assert report.main(argv) == 2, argv
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and err.startswith("report: error:") and needle in err, (argv, err)
    assert not (tmp_path / "o").exists()  # a bad flag writes nothing
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "analysis.report",
            "--experiment",
            "sweep_V10",
            "--tracking-uri",
            a,
            "--out",
            str(a_file),
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.strip().count("\n") == 0 and "is a file" in proc.stderr


def test_cells_joining_different_budgets_warn():
    import dataclasses

    from analysis.data import organise

    def rec(i, budget, exp):
        params = {"stop.env_steps": budget, "scenario.episode_len": "150"}
        run = finished_record(i, "mappo", seed=str(i), params=params, metrics={"eval/ee_sys_mean": 1.0})
        return dataclasses.replace(run, experiment=exp)

    org = organise([rec(0, "1000", "a"), rec(1, "1000", "a"), rec(2, "2000", "b")])
    # one run per cell, but the learner and the reference evaluated on different episodes: also named
    learner, ref = rec(0, "1000", "a"), rec(1, "1000", "b")
    learner.params["eval.episodes"], ref.params["eval.episodes"] = "2", "5"
    ref.kind, ref.algorithm, ref.seed = "baseline", "optimal", "0"
    warned = organise([learner, ref]).warnings
    assert any(
        "V=10 U=2: its runs were evaluated on different numbers of episodes (eval.episodes 2: mappo; 5: optimal)" in w
        for w in warned
    ), warned
    assert any("differ in stop.env_steps (1000 / 2000)" in w for w in org.warnings), org.warnings
    # a learner of another action mode than its reference's runs: another task, named
    learner, ref = rec(0, "1000", "a"), rec(1, "1000", "b")
    learner.params["scenario.action_mode"], ref.params["scenario.action_mode"] = "per_device", "per_uav"
    ref.kind, ref.algorithm, ref.seed = "baseline", "optimal", "0"
    assert any(
        "V=10 U=2: its algorithms ran different scenarios (scenario.action_mode per_device: mappo; per_uav: optimal)"
        in w
        for w in organise([learner, ref]).warnings
    )
    assert not any("differ" in w for w in organise([rec(0, "1000", "a"), rec(1, "1000", "b")]).warnings)
