"""The analysis step on a synthetic MLflow store with known numbers, and the animation CLI.

Store (sqlite in tmp_path), scenarios S1 = (V=10, U=2) and S2 = (V=20, U=2):
  learners  mappo  S1 seeds 0/42/2021 -> EE 100/110/120 (+ a FINISHED seed-99 run WITHOUT eval)
                   S2 seeds 0/42/2021/7 -> 50/60/70/200 (mean 95, IQM 65)
            vdn    S1 -> 80/85/90;  S2 seeds 0/42 -> 40/44 (2 seeds) + seed 2021 FAILED, no eval
            hyper_mix (a "new" algorithm) S1 -> 88/90/92 (second best in S1)
  baselines optimal 200 (S1) / 190 (S2), greedy 150 / 140 (3 seeds each), random 10/20/30 (S1), 5 (S2, 1 seed),
            best_fixed 196 (S1) / 95 (S2)
Training curves (train runs, step = env steps 0..10000): value = seed_offset + slope * step.
Execution curves (the periodic greedy evaluation, train runs with eval): eval/ee_sys_mean at env
steps 0, 2500, 5000, 7500 = EE * (0.5 + 0.5 step / 10000), and the final evaluation EE at 10000.
"""

from __future__ import annotations

import csv
import math
import os
import socket
import subprocess
import sys
import time

import numpy as np
import pytest
from scipy import stats as st

mlflow = pytest.importorskip("mlflow")
from mlflow.entities import Metric, Param  # noqa: E402
from mlflow.tracking import MlflowClient  # noqa: E402

from analysis import report, stats  # noqa: E402
from analysis.data import organise  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
EXP = "synthetic"
S1, S2 = (10, 2), (20, 2)
SEEDS = ("0", "42", "2021")
EE = {
    ("mappo", S1): dict(zip(SEEDS, (100.0, 110.0, 120.0))),
    ("mappo", S2): {"0": 50.0, "42": 60.0, "2021": 70.0, "7": 200.0},
    ("vdn", S1): dict(zip(SEEDS, (80.0, 85.0, 90.0))),
    ("vdn", S2): {"0": 40.0, "42": 44.0},
    ("hyper_mix", S1): dict(zip(SEEDS, (88.0, 90.0, 92.0))),
}
BASE = {
    ("optimal", S1): dict(zip(SEEDS, (200.0,) * 3)),
    ("optimal", S2): dict(zip(SEEDS, (190.0,) * 3)),
    ("greedy", S1): dict(zip(SEEDS, (150.0,) * 3)),
    ("greedy", S2): dict(zip(SEEDS, (140.0,) * 3)),
    ("random", S1): dict(zip(SEEDS, (10.0, 20.0, 30.0))),
    ("random", S2): {"0": 5.0},
    ("best_fixed", S1): dict(zip(SEEDS, (196.0,) * 3)),  # 0.98 of the optimum: a constant is optimal
    ("best_fixed", S2): dict(zip(SEEDS, (95.0,) * 3)),  # 0.5
}
SLOPE = {"mappo": 0.01, "vdn": 0.005, "hyper_mix": 0.002}
STEPS = np.arange(0, 10_001, 500)
EPISODE_LEN = 8
EVAL_STEPS = (0, 2500, 5000, 7500)


def ramp(step: float) -> float:
    return 0.5 + 0.5 * step / 10_000


def _make_run(client, exp_id, tmp_path, kind, alg, scen, seed, ee, status="FINISHED", curve_upto=None):
    tags = {
        "kind": kind,
        "algorithm": alg,
        "seed": seed,
        "n_eds": str(scen[0]),
        "n_uavs": str(scen[1]),
        "git_commit": "abc1234",
        "grid_file": "tune_configs/synthetic.yaml",
        "trial_id": f"{alg}_{scen[0]}_{scen[1]}_{seed}",
        "budget_env_steps": "10000",
    }
    if kind == "train":
        tags["checkpoint"] = str(tmp_path / "no_such_checkpoint" / tags["trial_id"])
    run = client.create_run(exp_id, run_name=tags["trial_id"], tags=tags)
    params = [
        Param("scenario.n_eds", str(scen[0])),
        Param("scenario.n_uavs", str(scen[1])),
        Param("scenario.episode_len", str(EPISODE_LEN)),
        Param("scenario.tp_dbm", "[2.0, 5.0, 8.0, 11.0, 14.0]"),
        Param("scenario.mobility.memory", "0.85"),
        Param("scenario.max_eds_per_uav", "None"),
        Param("scenario.quota", "8"),
        Param("eval.episodes", "10"),
    ]
    if kind == "train":
        params.append(Param("stop.env_steps", "10000"))
    now = int(time.time() * 1000)
    metrics = []
    final = int(STEPS[-1]) if kind == "train" else 0
    if ee is not None:
        metrics += [
            Metric("eval/ee_sys_mean", ee, now, final),
            Metric("eval/ee_sys_episode_sum", ee * EPISODE_LEN, now, final),
            Metric("eval/success_rate", 0.9, now, final),
            Metric("eval/episodes", 10, now, final),
        ]
        if kind == "train":
            metrics += [Metric("eval/ee_sys_mean", ee * ramp(s), now, s) for s in EVAL_STEPS]
            metrics.append(Metric("eval_sampled/ee_sys_mean", SAMPLED_FACTOR * ee, now, final))
    if kind == "train":
        off = float(SEEDS.index(seed)) if seed in SEEDS else 3.0
        upto = STEPS if curve_upto is None else STEPS[STEPS <= curve_upto]
        metrics += [Metric("episode_return_mean", off + SLOPE[alg] * s, now, int(s)) for s in upto]
    client.log_batch(run.info.run_id, metrics=metrics, params=params)
    client.set_terminated(run.info.run_id, status)
    return run.info.run_id


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    tmp_path = tmp_path_factory.mktemp("mlstore")
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    client = MlflowClient(tracking_uri=uri)
    exp_id = client.create_experiment(EXP, artifact_location=str(tmp_path / "artifacts"))
    client.create_experiment("other_experiment", artifact_location=str(tmp_path / "artifacts2"))
    for (alg, scen), by_seed in EE.items():
        for seed, ee in by_seed.items():
            _make_run(client, exp_id, tmp_path, "train", alg, scen, seed, ee)
    for (alg, scen), by_seed in BASE.items():
        for seed, ee in by_seed.items():
            _make_run(client, exp_id, tmp_path, "baseline", alg, scen, seed, ee)
    _make_run(client, exp_id, tmp_path, "train", "mappo", S1, "99", None)  # finished, no eval
    _make_run(client, exp_id, tmp_path, "train", "vdn", S2, "2021", None, status="FAILED", curve_upto=3000)
    out = tmp_path / "report"
    rc = report.main(["--experiment", EXP, "--tracking-uri", uri, "--out", str(out), "--smooth", "0", "--points", "21"])
    assert rc == 0
    return {"uri": uri, "out": out, "client": client, "exp_id": exp_id, "tmp": tmp_path}


def _rows(path):
    with open(path) as fh:
        return list(csv.DictReader(fh))


def _cell(rows, alg, scen):
    hits = [r for r in rows if r["algorithm"] == alg and (int(r["n_eds"]), int(r["n_uavs"])) == scen]
    assert len(hits) == 1, (alg, scen, hits)
    return hits[0]


SAMPLED_FACTOR = 0.8  # the synthetic learners' sampled execution EE, relative to their greedy EE


def _t_half(x):
    x = np.asarray(x, float)
    return st.t.ppf(0.975, len(x) - 1) * x.std(ddof=1) / math.sqrt(len(x))


def test_ee_table_means_ci_iqm(store):
    rows = _rows(store["out"] / "table_ee.csv")
    for (alg, scen), by_seed in {**EE, **BASE}.items():
        r = _cell(rows, alg, scen)
        x = np.array(list(by_seed.values()))
        assert int(r["n_seeds"]) == len(x)
        assert float(r["ee_mean"]) == pytest.approx(x.mean(), rel=1e-12)
        assert float(r["ee_iqm"]) == pytest.approx(st.trim_mean(x, 0.25), rel=1e-12)
        if len(x) >= 2:
            lo, hi = float(r["ee_ci95_low"]), float(r["ee_ci95_high"])
            assert lo <= float(r["ee_mean"]) <= hi
            assert lo == pytest.approx(x.mean() - _t_half(x), rel=1e-9, abs=1e-9)
            assert hi == pytest.approx(x.mean() + _t_half(x), rel=1e-9, abs=1e-9)
        else:
            assert r["ee_ci95_low"] == "" and r["ee_ci95_high"] == ""
    # hand-computed values, independent of the helpers above
    m2 = _cell(rows, "mappo", S2)
    assert float(m2["ee_mean"]) == 95.0 and float(m2["ee_iqm"]) == 65.0
    m1 = _cell(rows, "mappo", S1)
    assert float(m1["ee_ci95_high"]) == pytest.approx(110.0 + 4.302652729911275 * 10.0 / math.sqrt(3), rel=1e-9)
    assert m1["seeds"].split() == ["0", "2021", "42"]  # the seed-99 run without eval does not count
    assert float(m1["success_rate_mean"]) == pytest.approx(0.9)
    assert float(m1["ee_episode_sum_mean"]) == pytest.approx(110.0 * EPISODE_LEN)
    assert int(_cell(rows, "vdn", S2)["n_unfinished"]) == 1
    # the sampled execution sits beside the greedy one, for learners only
    assert float(m1["sampled_ee_mean"]) == pytest.approx(SAMPLED_FACTOR * 110.0)
    if m1["reference_baseline"]:
        ref = float(m1["ee_mean"]) / float(m1["share_of_reference"])
        assert float(m1["sampled_share_of_reference"]) == pytest.approx(SAMPLED_FACTOR * 110.0 / ref)
    for alg, scen in BASE:
        assert _cell(rows, alg, scen)["sampled_ee_mean"] in ("", "nan")
    assert int(m1["n_without_eval"]) == 1


def test_improvements_and_share_of_optimum(store):
    rows = _rows(store["out"] / "table_ee.csv")
    assert float(_cell(rows, "mappo", S1)["share_of_reference"]) == pytest.approx(110.0 / 200.0)
    # over the seeds the reference also ran (seed 7 has no optimal run): the same evaluation episodes
    assert float(_cell(rows, "mappo", S2)["share_of_reference"]) == pytest.approx(60.0 / 190.0)
    assert float(_cell(rows, "mappo", S2)["ee_mean"]) == pytest.approx(95.0)  # the EE columns keep every seed
    assert float(_cell(rows, "mappo", S2)["sampled_share_of_reference"]) == pytest.approx(SAMPLED_FACTOR * 60.0 / 190.0)
    assert float(_cell(rows, "optimal", S1)["share_of_reference"]) == pytest.approx(1.0)
    assert {r["reference_baseline"] for r in rows} == {"optimal"}  # the optimum wins over greedy
    assert float(_cell(rows, "vdn", S1)["reference_improvement_pct"]) == pytest.approx(100 * 25 / 85)
    imp = _rows(store["out"] / "table_improvement.csv")
    by = {(int(r["n_eds"]), r["other"]): r for r in imp}
    assert float(by[(10, "hyper_mix")]["improvement_pct"]) == pytest.approx(100.0 * (110 - 90) / 90)  # 22.22
    assert float(by[(10, "vdn")]["improvement_pct"]) == pytest.approx(100.0 * (110 - 85) / 85)  # 29.41
    assert float(by[(20, "vdn")]["improvement_pct"]) == pytest.approx(100.0 * (95 - 42) / 42)  # 126.19
    assert float(by[(10, "optimal")]["improvement_pct"]) == pytest.approx(-45.0)
    second = {int(r["n_eds"]): r["other"] for r in imp if r["is_second_best"] == "True"}
    assert second == {10: "hyper_mix", 20: "vdn"}  # best OTHER learner; baselines never count
    md = (store["out"] / "table_improvement.md").read_text()
    assert "+22.22" in md and "+126.19" in md


def test_open_loop_table_and_statement(store):
    rows = {(int(r["n_eds"]), int(r["n_uavs"])): r for r in _rows(store["out"] / "table_open_loop.csv")}
    assert float(rows[S1]["best_fixed_share_of_reference"]) == pytest.approx(0.98)
    assert rows[S1]["constant_is_optimal"] == "true" and rows[S2]["constant_is_optimal"] == "false"
    assert rows[S1]["reference_baseline"] == "optimal" and rows[S1]["action_mode"] == "per_uav"
    text = (store["out"] / "report.md").read_text()
    assert "## Open-loop check and the reference" in text
    assert "V=10 U=2 (per_uav): a constant action is optimal here" in text
    assert "V=20 U=2 (per_uav): best_fixed reaches 0.500" in text


def test_figures_and_curves(store):
    out = store["out"]
    for stem in ("fig2", "fig3a", "fig3a_all", "fig3b"):
        for ext in ("png", "svg"):
            p = out / f"{stem}.{ext}"
            assert p.is_file() and p.stat().st_size > 1000, p
    with open(out / "fig3b.png", "rb") as fh:
        assert fh.read(8) == b"\x89PNG\r\n\x1a\n"
    import matplotlib.image as mpimg

    h, w = mpimg.imread(str(out / "fig3b.png")).shape[:2]
    assert w == pytest.approx(3.5 * 300, abs=2)  # one paper column at 300 dpi
    import matplotlib

    assert matplotlib.rcParams["font.size"] == matplotlib.rcParamsDefault["font.size"]  # style not leaked
    assert not (out / "fig3c.png").exists()  # one U value only: skipped, with a note
    text = (out / "report.md").read_text()
    assert "Fig. 3c skipped" in text
    assert "greedy" in text.split("### Fig. 2")[1].split("###")[0]  # no checkpoint: baseline fallback
    # curves: no smoothing; mappo S1 has 4 FINISHED runs with curves (seed offsets 0/1/2 and 3 for
    # the seed-99 run without eval: training happened) -> mean = 1.5 + slope * step
    curves = [
        r
        for r in _rows(out / "fig3a_curves.csv")
        if r["algorithm"] == "mappo" and r["n_eds"] == "10" and r["metric"] == "episode_return_mean"
    ]
    assert len(curves) == 21 and float(curves[-1]["env_steps"]) == 10_000 and curves[0]["n_seeds"] == "4"
    for r in curves:
        x, m = float(r["env_steps"]), float(r["mean"])
        assert m == pytest.approx(1.5 + SLOPE["mappo"] * x, abs=1e-9)
        assert float(r["ci95_low"]) <= m <= float(r["ci95_high"])
        assert float(r["ci95_low"]) >= 0.0 + SLOPE["mappo"] * x - 1e-9  # within the seeds' range
        assert float(r["ci95_high"]) <= 3.0 + SLOPE["mappo"] * x + 1e-9
    # the execution curve: raw EE per slot in the CSV, the reference named beside it
    ev = [
        r
        for r in _rows(out / "fig3a_curves.csv")
        if r["algorithm"] == "mappo" and r["n_eds"] == "10" and r["metric"] == "eval/ee_sys_mean"
    ]
    assert len(ev) == 21 and ev[0]["n_seeds"] == "3"  # the seed-99 run has no eval history
    for r in ev:
        assert float(r["mean"]) == pytest.approx(110.0 * ramp(float(r["env_steps"])), rel=1e-9)
        assert r["reference"] == "optimal" and float(r["reference_ee"]) == 200.0
    assert "greedy policy" in text and "share of the per-slot optimum" in text
    # S2: mappo's seed 7 has no optimal run, so its execution curve (divided by the optimum) leaves it
    # out, as every share of the report does; the training return keeps all four seeds
    ev2 = [
        r
        for r in _rows(out / "fig3a_curves.csv")
        if r["algorithm"] == "mappo" and r["n_eds"] == "20" and r["metric"] == "eval/ee_sys_mean"
    ]
    assert ev2 and {r["n_seeds"] for r in ev2} == {"3"} and {r["reference_ee"] for r in ev2} == {"190.0"}
    for r in ev2:
        assert float(r["mean"]) == pytest.approx(60.0 * ramp(float(r["env_steps"])), rel=1e-9)
    assert "V=20 U=2 mappo: seed(s) 7 left out of its eval/ee_sys_mean curve" in text
    # the FAILED vdn run's short curve is left out: the S2 grid spans the full budget
    vdn2 = [
        r
        for r in _rows(out / "fig3a_curves.csv")
        if r["algorithm"] == "vdn" and r["n_eds"] == "20" and r["metric"] == "episode_return_mean"
    ]
    assert float(vdn2[-1]["env_steps"]) == 10_000 and vdn2[0]["n_seeds"] == "2"


def test_aggregates_probability_of_improvement_and_profile(store):
    """table_aggregate, table_improvement_probability and fig_profile on the shares of each
    scenario's optimum (200 in S1, 190 in S2)."""
    out = store["out"]
    shares = {  # over the seeds the optimum ran: mappo's seed 7 of S2 has no reference of its own episodes
        alg: {
            scen: np.array([v for s, v in by_seed.items() if s in SEEDS]) / (200.0 if scen == S1 else 190.0)
            for (a, scen), by_seed in EE.items()
            if a == alg
        }
        for alg in ("mappo", "vdn", "hyper_mix")
    }
    agg = {r["algorithm"]: r for r in _rows(out / "table_aggregate.csv")}
    m = agg["mappo"]
    assert m["kind"] == "train" and m["n_scenarios"] == "2" and m["n_runs"] == "6" and m["scenarios"] == "V10U2 V20U2"
    pooled = np.concatenate(list(shares["mappo"].values()))
    assert float(m["iqm"]) == pytest.approx(st.trim_mean(pooled, 0.25), rel=1e-12)
    assert float(m["mean"]) == pytest.approx((110.0 / 200 + 60.0 / 190) / 2, rel=1e-12)  # scenarios weigh the same
    for name in ("iqm", "mean"):
        assert float(m[f"{name}_ci95_low"]) <= float(m[name]) <= float(m[f"{name}_ci95_high"])
    assert float(agg["optimal"]["iqm"]) == pytest.approx(1.0) and agg["hyper_mix"]["scenarios"] == "V10U2"
    assert [r["algorithm"] for r in _rows(out / "table_aggregate.csv")][:3] == ["hyper_mix", "mappo", "vdn"]  # by IQM
    poi = {r["other"]: r for r in _rows(out / "table_improvement_probability.csv")}
    assert set(poi) == {"vdn", "hyper_mix", "best_fixed"} and {r["reference"] for r in poi.values()} == {"mappo"}
    assert float(poi["vdn"]["probability_of_improvement"]) == 1.0 and poi["vdn"]["n_scenarios"] == "2"
    assert float(poi["hyper_mix"]["probability_of_improvement"]) == 1.0 and poi["hyper_mix"]["scenarios"] == "V10U2"
    # best_fixed: 0.98 of the optimum in S1, 0.5 in S2: above every matched mappo seed (seed 7 is left out)
    assert float(poi["best_fixed"]["probability_of_improvement"]) == pytest.approx(0.0)
    for stem in ("png", "svg"):
        assert (out / f"fig_profile.{stem}").stat().st_size > 1000
    prof = _rows(out / "fig_profile.csv")
    assert {r["algorithm"] for r in prof} == {"mappo", "vdn", "hyper_mix", "best_fixed"}
    mp = [r for r in prof if r["algorithm"] == "mappo"]
    fr = np.array([float(r["fraction_above"]) for r in mp])
    assert fr[0] == 1.0 and fr[-1] == 0.0 and np.all(np.diff(fr) <= 0) and mp[0]["n_runs"] == "6"
    for r in mp:  # the fraction of runs above tau, each scenario weighing one half
        tau = float(r["tau"])
        want = np.mean([np.mean(v > tau) for v in shares["mappo"].values()])
        assert float(r["fraction_above"]) == pytest.approx(want)
        assert float(r["ci95_low"]) <= float(r["fraction_above"]) <= float(r["ci95_high"])
    text = (out / "report.md").read_text()
    assert "## Aggregate over seeds and scenarios" in text and "share of its scenario's reference" in text
    for link in ("table_aggregate.csv", "table_improvement_probability.csv", "fig_profile.png", "fig_profile.csv"):
        assert f"({link})" in text, link
    assert "P(mappo > other)" in text and "the learners cover different scenarios" in text  # hyper_mix: S1 only
    assert "docs/model.md#aggregate-statistics" in text


def test_report_warnings_and_source(store):
    text = (store["out"] / "report.md").read_text()
    warn = [ln for ln in text.splitlines() if "WARNING" in ln]
    assert any("V=20 U=2 vdn" in w and "only 2 seed(s)" in w for w in warn)
    assert any("unfinished" in w and "vdn" in w and "FAILED" in w for w in warn)
    assert any("without eval metrics" in w and "seed=99" in w for w in warn)
    assert any("V=20 U=2 random" in w and "only 1 seed(s)" in w for w in warn)
    assert not any("V=10 U=2 mappo (train): only" in w for w in warn)
    assert any("V=20 U=2 mappo (train): seed(s) 7 have no optimal run" in w for w in warn)
    for needed in ("tune_configs/synthetic.yaml", "abc1234", "10000", "0, 2021, 42"):
        assert needed in text, needed
    for link in ("fig2.png", "fig3a.png", "fig3b.png", "table_ee.csv", "table_improvement.csv"):
        assert f"({link})" in text


def test_summary_run_logged_and_replaced(store):
    client = store["client"]

    def summaries():
        return [r for r in client.search_runs([store["exp_id"]]) if r.data.tags.get("kind") == "summary"]

    first = summaries()
    assert len(first) == 1 and first[0].info.status == "FINISHED"
    names = {a.path for a in client.list_artifacts(first[0].info.run_id)}
    assert {"report.md", "table_ee.csv", "fig3a.png", "fig3b.svg"} <= names
    out2 = store["tmp"] / "report2"
    assert report.main(["--experiment", EXP, "--tracking-uri", store["uri"], "--out", str(out2), "--no-fig2"]) == 0
    again = summaries()
    assert [r.info.run_id for r in again] == [first[0].info.run_id]  # reused, not piled up
    names = {a.path for a in client.list_artifacts(again[0].info.run_id)}
    assert "fig2.png" not in names and "report.md" in names  # previous artifacts replaced


def test_a_report_stopped_while_writing_leaves_the_previous_one_whole(store, monkeypatch, capsys):
    from analysis import report_files

    out = store["tmp"] / "report_whole"
    argv = ["--experiment", EXP, "--tracking-uri", store["uri"], "--out", str(out), "--no-log"]
    assert report.main(argv) == 0
    (out / "notes.txt").write_text("mine")  # not the report's: never touched

    def files() -> dict[str, bytes]:
        return {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}

    before = files()
    assert "fig2.png" in before and "report.md" in before

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    with monkeypatch.context() as m:  # Ctrl+C after the tables and figures were written
        m.setattr(report_files, "write_aggregates", interrupted)
        assert report.main([*argv, "--no-fig2"]) == 130
    assert "previous report, if any, unchanged" in capsys.readouterr().err
    assert files() == before and sorted(p.name for p in out.iterdir() if p.is_dir()) == []
    assert report.main([*argv, "--no-fig2"]) == 0  # a complete report replaces it, stale figures removed
    after = files()
    assert (
        "fig2.png" not in after
        and after["notes.txt"] == b"mine"
        and set(after) == set(before) - {"fig2.png", "fig2.svg"}
    )
    assert not any(p.name.startswith(report_files.STAGING) for p in out.iterdir())
    host = socket.gethostname()
    dead = out / f"{report_files.STAGING}-{host}-999999999"  # a report killed outright left it (no such process)
    dead.mkdir()
    mine = out / f"{report_files.STAGING}-{host}-{os.getppid()}"  # a running report's (this process's parent)
    mine.mkdir()
    assert report.main([*argv, "--no-fig2"]) == 0
    assert not dead.exists() and mine.exists()


def test_bad_experiment_and_uri(store, tmp_path, capsys):
    assert report.main(["--experiment", "nope", "--tracking-uri", store["uri"], "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "'nope' not found" in err and "'synthetic'" in err and "'other_experiment'" in err
    missing = f"sqlite:///{tmp_path / 'absent' / 'mlflow.db'}"
    assert report.main(["--experiment", EXP, "--tracking-uri", missing]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and missing in err and "unreachable" in err
    assert not (tmp_path / "absent").exists()
    # an unreachable server: one line naming it (MLflow's retries are off by default here)
    assert report.main(["--experiment", EXP, "--tracking-uri", "http://127.0.0.1:9"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "http://127.0.0.1:9" in err and "unreachable" in err
    # through the module entry point: one line, exit code 2, no traceback
    proc = subprocess.run(
        [sys.executable, "-m", "analysis.report", "--experiment", "nope", "--tracking-uri", missing],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr and proc.stderr.strip().count("\n") == 0
    assert proc.stderr.startswith("report: error:") and missing in proc.stderr


def test_stats_definitions():
    x = [1.0, 2.0, 3.0, 10.0]
    s = stats.summarize(x)
    assert s.mean == 4.0 and s.iqm == 2.5 and s.n == 4
    assert stats.summarize([3.0]).ci_low != stats.summarize([3.0]).ci_low  # NaN for one seed
    assert stats.improvement_pct(110.0, 85.0) == pytest.approx(29.411764705882355)
    assert math.isnan(stats.improvement_pct(1.0, 0.0))
    e = stats.ema([1.0, 1.0, 1.0], 0.9)
    assert np.allclose(e, 1.0)  # debiased: a constant stays constant
    assert np.allclose(stats.ema([0.0, 10.0], 0.5), [0.0, 10.0 * 0.5 / 0.75])
    assert stats.common_grid([(0, 10), (2, 8)], 4).tolist() == [2.0, 4.0, 6.0, 8.0]
    assert stats.common_grid([(0, 1), (2, 3)]).size == 0
    assert organise([]).warnings == []


def test_colours_deterministic_for_new_names():
    from analysis import style

    a = style.colour_map(["mappo", "zeta_algo", "alpha_algo", "vdn"])
    b = style.colour_map(["vdn", "alpha_algo", "mappo", "zeta_algo"])
    assert a == b and a["mappo"] == style.KNOWN_COLOURS["mappo"]
    assert len(set(a.values())) == 4


def test_animate_writes_gif(tmp_path):
    import imageio.v3 as iio

    from analysis import animate

    out = tmp_path / "anim.gif"
    assert animate.main(["--policy", "greedy", "--n-eds", "4", "--n-uavs", "2", "--steps", "5", "--out", str(out)]) == 0
    frames = iio.imread(out, index=None)
    assert frames.shape[0] == 6 and frames.ndim == 4  # reset frame + one per step
    assert animate.main(["--policy", "nonsense", "--out", str(tmp_path / "x.gif")]) == 2
    assert animate.main(["--policy", "random", "--steps", "151", "--out", str(tmp_path / "y.gif")]) == 2


def test_animate_error_paths_one_line(tmp_path, capsys):
    from analysis import animate

    folder = tmp_path / "a.gif"
    folder.mkdir()
    blocker = tmp_path / "file"
    blocker.write_text("x")
    cases = [
        (["--policy", "greedy", "--out", str(folder)], "is a folder"),
        (["--policy", "greedy", "--out", str(blocker / "x.gif")], "cannot create the folder"),
        (["--policy", "greedy", "--out", str(tmp_path / "x.png")], "expected a .gif"),
        (["--policy", str(tmp_path), "--out", str(tmp_path / "y.gif")], "is not an RLlib checkpoint"),
        (["--policy", "greedy", "--seed", "x", "--out", str(tmp_path / "z.gif")], "--seed"),
    ]
    for argv, needle in cases:
        assert animate.main(argv) == 2, argv
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and err.startswith("animate: error:") and needle in err, (argv, err)
    assert not (tmp_path / "y.gif").exists() and not (tmp_path / "z.gif").exists()
