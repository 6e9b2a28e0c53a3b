"""Bad command-line input to analysis.animate, analysis.report, analysis.archive and the
docs/history/measurements bench scripts: one line on stderr naming the flag (or argument), exit
code 2, before any long work (a simulation, an export, a training run). No Ray, no training."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
EXP = "cli_input"
SMALL = ["--n-eds", "4", "--n-uavs", "2", "--steps", "1"]


def _one_line(capsys, prog: str, needle: str) -> str:
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith(f"{prog}: error: ") and needle in err, err
    return err


def _no_simulation(monkeypatch):
    from analysis import animate

    def fail(*args, **kwargs):
        raise AssertionError("the episode was played before the input was checked")

    monkeypatch.setattr(animate, "record_frames", fail)


# --- analysis.animate


@pytest.mark.parametrize("value", ["-1", "99999999999999999999999", "4294967296"])
def test_animate_seed_out_of_range(value, tmp_path, capsys, monkeypatch):
    from analysis import animate

    _no_simulation(monkeypatch)
    assert animate.main(["--policy", "random", "--seed", value, "--out", str(tmp_path / "a.gif"), *SMALL]) == 2
    _one_line(capsys, "animate", "--seed: must be an integer in [0, 4294967295]")


def test_animate_largest_seed_plays(tmp_path):
    from analysis import animate

    out = tmp_path / "a.gif"
    assert animate.main(["--policy", "random", "--seed", str(2**32 - 1), "--out", str(out), *SMALL]) == 0
    assert out.stat().st_size > 0


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs Linux's /proc, where no file can be created")
def test_animate_unwritable_out_before_simulating(capsys, monkeypatch):
    from analysis import animate

    _no_simulation(monkeypatch)
    assert animate.main(["--policy", "random", "--out", "/proc/x.gif", *SMALL]) == 2
    _one_line(capsys, "animate", "--out: cannot write to the folder '/proc'")


@pytest.mark.parametrize("value", ["0", "101", "100000000"])
def test_animate_fps_bounded(value, tmp_path, capsys, monkeypatch):
    from analysis import animate

    _no_simulation(monkeypatch)
    assert animate.main(["--policy", "random", "--fps", value, "--out", str(tmp_path / "a.gif"), *SMALL]) == 2
    _one_line(capsys, "animate", "--fps: must be an integer in [1, 100]")


def test_animate_fps_100_accepted():
    from analysis import animate

    assert animate.build_parser().parse_args(["--policy", "random", "--fps", "100"]).fps == 100


def test_animate_empty_dir_is_not_a_checkpoint(tmp_path):
    """One line, as evaluate gives it, and no RLlib warning before it (a subprocess sees all of stderr)."""
    empty = tmp_path / "empty"
    empty.mkdir()
    proc = subprocess.run(
        [sys.executable, "-m", "analysis.animate", "--policy", str(empty), "--out", str(tmp_path / "a.gif")],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=300,
    )
    assert proc.returncode == 2
    expected = f"animate: error: --policy: {str(empty)!r} is not an RLlib checkpoint (no rllib_checkpoint.json)\n"
    assert proc.stderr == expected


# --- analysis.report and analysis.archive: a small store


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    mlflow = pytest.importorskip("mlflow")
    from mlflow.entities import Metric, Param

    tmp = tmp_path_factory.mktemp("cli_input")
    uri = f"sqlite:///{tmp / 'mlflow.db'}"
    client = mlflow.tracking.MlflowClient(tracking_uri=uri)
    exp = client.create_experiment(EXP, artifact_location=str(tmp / "art"))
    now = int(time.time() * 1000)
    for kind, alg, ee in (("train", "mappo", 100.0), ("train", "qmix", 80.0), ("baseline", "greedy", 150.0)):
        for seed in (0, 1):
            tags = {"kind": kind, "algorithm": alg, "seed": str(seed), "n_eds": "10", "n_uavs": "2"}
            rid = client.create_run(exp, run_name=f"{alg}-s{seed}", tags=tags).info.run_id
            params = [Param("scenario.n_eds", "10"), Param("scenario.n_uavs", "2"), Param("eval.episodes", "10")]
            client.log_batch(rid, metrics=[Metric("eval/ee_sys_mean", ee + seed, now, 1000)], params=params)
            client.set_terminated(rid, "FINISHED")
    return {"uri": uri, "tmp": tmp}


def _report(store, *extra: str, out: str | None = None) -> int:
    from analysis import report

    out = str(store["tmp"] / "report") if out is None else out
    return report.main(["--experiment", EXP, "--tracking-uri", store["uri"], "--out", out, "--no-log", *extra])


def test_report_points_bounded(store, capsys):
    assert _report(store, "--points", "1000000000") == 2
    _one_line(capsys, "report", "--points: must be an integer in [2, 100000]")


def test_report_unknown_reference_refused(store, capsys):
    out = store["tmp"] / "ref_foo"
    assert _report(store, "--reference", "foo", "--no-fig2", out=str(out)) == 2
    _one_line(capsys, "report", "--reference: 'foo' has no training runs; learners: mappo, qmix")
    assert not out.exists()  # refused before anything is written


def test_report_reference_given_or_default(store, tmp_path):
    assert _report(store, "--reference", "QMIX", "--no-fig2", out=str(tmp_path / "q")) == 0
    assert "Improvement of qmix" in (tmp_path / "q" / "report.md").read_text()


@pytest.mark.parametrize("flag", [["--fig2-algorithm", "mappo"], ["--fig2-seed", "3"], ["--fig2-seed", "0"]])
def test_report_fig2_flag_with_no_fig2_refused(store, capsys, flag):
    assert _report(store, *flag, "--no-fig2") == 2
    _one_line(capsys, "report", f"{flag[0]}: applies to Fig. 2, which --no-fig2 skips")


def test_report_empty_out_refused(store, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert _report(store, "--no-fig2", out="") == 2
    _one_line(capsys, "report", "--out: empty path")
    assert not (tmp_path / "reports").exists()


def test_archive_export_empty_out_refused(store, capsys, tmp_path, monkeypatch):
    from analysis import archive

    monkeypatch.chdir(tmp_path)
    assert archive.main(["export", "--experiment", EXP, "--tracking-uri", store["uri"], "--out", ""]) == 2
    _one_line(capsys, "archive", "--out: empty path")
    assert list(tmp_path.iterdir()) == []


def _no_export(monkeypatch):
    from analysis import archive

    def fail(*args, **kwargs):
        raise AssertionError("runs were exported before --out was checked")

    monkeypatch.setattr(archive, "_run_record", fail)


def test_archive_export_out_directory_refused_up_front(store, capsys, tmp_path, monkeypatch):
    from analysis import archive

    _no_export(monkeypatch)
    monkeypatch.chdir(tmp_path)
    assert archive.main(["export", "--experiment", EXP, "--tracking-uri", store["uri"], "--out", str(tmp_path)]) == 2
    assert _one_line(capsys, "archive", "--out:").endswith(f"--out: {tmp_path} is a directory; expected a file name")
    assert list(tmp_path.iterdir()) == []  # no temporary file left anywhere near


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs Linux's /proc, where no file can be created")
def test_archive_export_unwritable_out_refused_up_front(store, capsys, monkeypatch):
    from analysis import archive

    _no_export(monkeypatch)
    assert archive.main(["export", "--experiment", EXP, "--tracking-uri", store["uri"], "--out", "/proc/x.gz"]) == 2
    _one_line(capsys, "archive", "--out: cannot write to the folder '/proc'")


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs Linux's /proc, where no folder can be created")
def test_archive_restore_unwritable_store_refused_up_front(store, capsys, tmp_path, monkeypatch):
    from analysis import archive

    path = tmp_path / "a.mlflow.json.gz"
    assert archive.main(["export", "--experiment", EXP, "--tracking-uri", store["uri"], "--out", str(path)]) == 0
    capsys.readouterr()

    def fail(*args, **kwargs):
        raise AssertionError("a run was restored before --tracking-uri was checked")

    monkeypatch.setattr(archive, "_restore_run", fail)
    assert archive.main(["restore", str(path), "--tracking-uri", "sqlite:////proc/x/r.db"]) == 2
    _one_line(capsys, "archive", "--tracking-uri: cannot create the folder '/proc/x'")


def test_tracking_uri_naming_a_directory(store, capsys, tmp_path):
    from analysis import archive, report

    uri = f"sqlite:///{tmp_path}"
    needle = f"--tracking-uri: {uri!r} names the directory {tmp_path}"
    assert report.main(["--experiment", EXP, "--tracking-uri", uri, "--out", str(tmp_path / "r")]) == 2
    _one_line(capsys, "report", needle)
    assert archive.main(["export", "--experiment", EXP, "--tracking-uri", uri, "--out", str(tmp_path / "a.gz")]) == 2
    _one_line(capsys, "archive", needle)


# --- docs/history/measurements: the bench scripts (a stub PY, so that no training runs)

BENCH = ["bench_coma_pair.sh", "bench_gamma0.sh", "bench_precision.sh"]


def _bench(script: str, args: list[str], py: str) -> subprocess.CompletedProcess:
    path = ROOT / "docs" / "history" / "measurements" / script
    env = {**os.environ, "PY": py}
    return subprocess.run(["bash", str(path), *args], capture_output=True, text=True, cwd=ROOT, env=env, timeout=60)


@pytest.fixture
def bench_inputs(tmp_path):
    stub = tmp_path / "stub_python"
    stub.write_text("#!/bin/sh\necho '{\"env_steps_per_s\": 1.0}'\n")
    stub.chmod(0o755)
    old = tmp_path / "old"
    (old / "uavlora_rllib").mkdir(parents=True)
    return {"py": str(stub), "old": str(old), "tmp": tmp_path}


@pytest.mark.parametrize("script", BENCH)
def test_bench_script_bad_arguments(script, bench_inputs):
    tmp, py, old = bench_inputs["tmp"], bench_inputs["py"], bench_inputs["old"]
    out = str(tmp / "out.jsonl")
    cases = [
        ([], py, f"usage: {script} OLD_CHECKOUT OUT.jsonl"),
        ([old], py, f"usage: {script} OLD_CHECKOUT OUT.jsonl"),
        ([str(tmp / "missing"), out], py, "OLD_CHECKOUT: no directory"),
        ([str(tmp), out], py, "OLD_CHECKOUT: "),  # a folder that is not a checkout of the project
        ([old, str(tmp)], py, f"OUT.jsonl: cannot append to {tmp}"),
        ([old, out], str(tmp / "no_python"), "no python at"),
        ([old, out], str(tmp), "no python at"),  # a folder is no interpreter
    ]
    if os.path.isdir("/proc/self"):
        cases.append(([old, "/proc/x"], py, "OUT.jsonl: cannot append to /proc/x"))
    for args, python, needle in cases:
        proc = _bench(script, args, python)
        assert proc.returncode == 2, (args, proc.returncode, proc.stderr)
        assert proc.stderr.count("\n") == 1 and needle in proc.stderr, (args, proc.stderr)
        assert not os.path.exists(out), args  # nothing ran


@pytest.mark.parametrize("script", BENCH)
def test_bench_script_runs_with_good_arguments(script, bench_inputs):
    out = bench_inputs["tmp"] / "out.jsonl"
    proc = _bench(script, [bench_inputs["old"], str(out)], bench_inputs["py"])
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr
    rows = out.read_text().splitlines()
    assert rows and all('"res":{"env_steps_per_s": 1.0}' in r for r in rows)
    out.unlink()  # a PY relative to the project root still runs in each checkout (the runs cd there)
    proc = _bench(script, [bench_inputs["old"], str(out)], os.path.relpath(bench_inputs["py"], ROOT))
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr
    assert all('"res":{"env_steps_per_s": 1.0}' in r for r in out.read_text().splitlines())


def test_bench_versions_script_checks_its_arguments(bench_inputs):
    tmp, py, old = bench_inputs["tmp"], bench_inputs["py"], bench_inputs["old"]
    out = str(tmp / "out.jsonl")
    usage = "usage: bench_versions.sh OUT.jsonl NAME=CHECKOUT..."
    cases = [
        ([], py, usage),
        ([out], py, usage),
        ([out, old], py, f"NAME=CHECKOUT: {old} is not"),  # no NAME=
        ([out, f"a={tmp / 'missing'}"], py, "NAME=CHECKOUT: a="),
        ([out, f"a={tmp}"], py, "NAME=CHECKOUT: a="),  # a folder that is not a checkout of the project
        ([str(tmp), f"a={old}"], py, f"OUT.jsonl: cannot append to {tmp}"),
        ([out, f"a={old}"], str(tmp / "no_python"), "no python at"),
        ([out, f"a={old}@fp16"], py, f"NAME=CHECKOUT: a={old}@fp16 is not"),  # only @float32 and @bfloat16 are suffixes
    ]
    for args, python, needle in cases:
        proc = _bench("bench_versions.sh", args, python)
        assert proc.returncode == 2, (args, proc.returncode, proc.stderr)
        assert proc.stderr.count("\n") == 1 and needle in proc.stderr, (args, proc.stderr)
        assert not os.path.exists(out), args  # nothing ran


def test_bench_versions_script_interleaves_and_reverses(bench_inputs, monkeypatch):
    tmp, old = bench_inputs["tmp"], bench_inputs["old"]
    out = tmp / "out.jsonl"
    monkeypatch.setenv("CASES", "mappo 8 per_uav,qmix 8 per_device")
    proc = _bench("bench_versions.sh", [str(out), f"old={old}", f"new={old}"], bench_inputs["py"])
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    # old is skipped for qmix per_device (6f5d51a has no such form); round 2 runs the checkouts in reverse
    got = [(r["round"], r["algo"], r["ver"]) for r in rows]
    assert got == [
        (1, "mappo", "old"),
        (1, "mappo", "new"),
        (1, "qmix", "new"),
        (2, "mappo", "new"),
        (2, "mappo", "old"),
        (2, "qmix", "new"),
    ]
    assert all(r["res"] == {"env_steps_per_s": 1.0} and r["commit"] == "none" for r in rows)


def test_bench_versions_script_passes_a_checkouts_precision(bench_inputs, monkeypatch):
    tmp, old = bench_inputs["tmp"], bench_inputs["old"]
    stub = tmp / "precision_python"  # reports whether bench_train was asked for bfloat16
    stub.write_text(
        '#!/bin/sh\ncase "$*" in *"--learner-precision bfloat16"*) b=true;; *) b=false;; esac\n'
        'echo "{\\"env_steps_per_s\\": 1.0, \\"bf16\\": $b}"\n'
    )
    stub.chmod(0o755)
    out = tmp / "out.jsonl"
    monkeypatch.setenv("CASES", "mappo 8 per_uav")
    at = tmp / "workspace@2"  # an @ in a path is no precision
    (at / "uavlora_rllib").mkdir(parents=True)
    proc = _bench("bench_versions.sh", [str(out), f"f32={old}@float32", f"bf16={old}@bfloat16", f"at={at}"], str(stub))
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    assert [(r["ver"], r["precision"], r["res"]["bf16"]) for r in rows] == [
        ("f32", "float32", False),
        ("bf16", "bfloat16", True),
        ("at", "float32", False),
        ("at", "float32", False),
        ("bf16", "bfloat16", True),
        ("f32", "float32", False),
    ]


def test_bench_versions_script_passes_a_cases_eds(bench_inputs, monkeypatch):
    tmp, old = bench_inputs["tmp"], bench_inputs["old"]
    stub = tmp / "eds_python"  # reports the --n-eds bench_train was given
    stub.write_text(
        '#!/bin/sh\nv=$(echo "$*" | sed -n "s/.*--n-eds \\([0-9]*\\).*/\\1/p")\necho "{\\"env_steps_per_s\\": 1.0, \\"v\\": $v}"\n'
    )
    stub.chmod(0o755)
    out = tmp / "out.jsonl"
    monkeypatch.setenv("CASES", "mappo 2 per_uav 10,qmix 8 per_uav")  # V: EDs, 60 if left out
    proc = _bench("bench_versions.sh", [str(out), f"new={old}"], str(stub))
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    assert [(r["algo"], r["V"], r["res"]["v"]) for r in rows] == [("mappo", 10, 10), ("qmix", 60, 60)] * 2
