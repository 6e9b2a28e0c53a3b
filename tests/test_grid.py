"""Grid YAML: validation messages name the YAML path, nothing starts on a bad grid, and the
trial product / dry-run table are right. No Ray here (fast)."""

from __future__ import annotations

import dataclasses
import os
import re
import subprocess
import sys

import pytest
import tune_stock_ppo  # noqa: F401  (registers stock_ppo, stock_ppo_b)
import yaml
from conftest import run_tune as run_cli
from conftest import write_grid as write

from uavlora_rllib.config_errors import ConfigError
from uavlora_rllib.experiment import sweep
from uavlora_rllib.experiment.grid import baseline_runs, load_grid, parse_grid, trials

TESTS_DIR = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(TESTS_DIR)


def base_grid(tmp_path) -> dict:
    return {
        "experiment": "g",
        "plugins": ["tune_stock_ppo"],
        "algorithms": {"stock_ppo": {"lr": 1e-3}, "stock_ppo_b": None},
        "baselines": ["random", "greedy"],
        "seeds": [0, 42, 2021],
        "n_eds": [5, 10],
        "n_uavs": [1, 2],
        "scenario": {"episode_len": 10},
        "stop": {"env_steps": 1000},
        "checkpoint_every": 2,
        "evaluation": {"episodes": 2},
        "storage": str(tmp_path / "ray_results"),
        "mlflow": {"tracking_uri": f"sqlite:///{tmp_path / 'mlflow.db'}"},
    }


# --------------------------------------------------------------------------- valid grids
def test_exponent_without_a_dot_is_a_number(tmp_path):
    """`lr: 3e-4` is a number, as in YAML 1.2 and Python (PyYAML alone reads it as text)."""
    text = yaml.safe_dump(base_grid(tmp_path), sort_keys=False).replace("lr: 0.001", "lr: 3e-4")
    assert "lr: 3e-4" in text
    grid = load_grid(write(tmp_path, text))
    assert {s.algorithm: getattr(s.hparams, "lr", None) for s in trials(grid)}["stock_ppo"] == pytest.approx(3e-4)


def test_valid_grid_and_trial_product(tmp_path):
    grid = load_grid(write(tmp_path, base_grid(tmp_path)))
    specs = trials(grid)
    assert len(specs) == 2 * 3 * 2 * 2
    keys = {(s.algorithm, s.seed, s.n_eds, s.n_uavs) for s in specs}
    assert len(keys) == len(specs)
    assert {s.algorithm for s in specs} == {"stock_ppo", "stock_ppo_b"}
    for s in specs:
        assert s.scenario.n_eds == s.n_eds and s.scenario.n_uavs == s.n_uavs
        assert s.scenario.episode_len == 10
    assert next(s for s in specs if s.algorithm == "stock_ppo").hparams.lr == 1e-3
    assert next(s for s in specs if s.algorithm == "stock_ppo_b").hparams.lr == 3e-4  # default
    assert specs[0].name == "stock_ppo-V5-U1-s0"
    base = baseline_runs(grid)
    assert len(base) == 2 * 3 * 2 * 2
    assert {b.name for b in base} >= {"random-V5-U1-s0", "greedy-V10-U2-s2021"}


def test_defaults(tmp_path):
    data = base_grid(tmp_path)
    for key in ("baselines", "scenario", "checkpoint_every", "evaluation", "storage", "mlflow"):
        data.pop(key)
    grid = load_grid(write(tmp_path, data))
    assert grid.baselines == [] and grid.scenario == {}
    assert grid.mlflow.tracking_uri == "sqlite:///mlflow.db"
    assert grid.evaluation.episodes == 10
    assert grid.storage == "./ray_results"
    assert grid.max_concurrent_trials is None


def test_algorithms_as_list(tmp_path):
    data = base_grid(tmp_path)
    data["algorithms"] = ["stock_ppo"]
    assert len(trials(load_grid(write(tmp_path, data)))) == 3 * 2 * 2


# --------------------------------------------------------------------------- bad grids
def _mutate(tmp_path, **changes):
    data = base_grid(tmp_path)
    for key, value in changes.items():
        if value is None:
            data.pop(key)
        else:
            data[key] = value
    return data


BAD = [
    # (id, mutation or raw text, regex the message must match after "<file>: ")
    ("unknown_top_level_key", {"epochs": 3}, r"epochs: unknown field; allowed: .*algorithms"),
    ("unknown_algorithm", {"algorithms": {"nosuch": None}}, r"algorithms\.nosuch: unknown algorithm 'nosuch'"),
    (
        "bad_override_value",
        {"algorithms": {"stock_ppo": {"lr": -1}}},
        r"algorithms\.stock_ppo\.lr: Input should be greater than 0 \(got -1\)",
    ),
    (
        "unknown_override",
        {"algorithms": {"stock_ppo": {"learning_rate": 1}}},
        r"algorithms\.stock_ppo\.learning_rate: unknown field",
    ),
    ("override_not_mapping", {"algorithms": {"stock_ppo": 5}}, r"algorithms\.stock_ppo: "),
    ("bad_scenario_value", {"scenario": {"sf_set": [5]}}, r"scenario\.sf_set: must be distinct values"),
    ("unknown_scenario_field", {"scenario": {"n_gateways": 3}}, r"scenario\.n_gateways: unknown field"),
    ("scenario_sets_n_eds", {"scenario": {"n_eds": 3}}, r"scenario\.n_eds: set by the top-level 'n_eds' list"),
    (
        "action_mode_mismatch",
        {"scenario": {"action_mode": "per_device"}},
        r"scenario\.action_mode: algorithm 'stock_ppo' supports action modes \['per_uav'\]",
    ),
    ("empty_seeds", {"seeds": []}, r"seeds: List should have at least 1 item"),
    ("empty_n_eds", {"n_eds": []}, r"n_eds: List should have at least 1 item"),
    ("empty_algorithms", {"algorithms": {}}, r"algorithms: Dictionary should have at least 1 item"),
    ("bad_n_uavs", {"n_uavs": [2, 0]}, r"n_uavs\.1: Input should be greater than or equal to 1"),
    ("repeated_seed", {"seeds": [1, 1]}, r"seeds: values must be distinct"),
    ("missing_stop", {"stop": None}, r"stop: required field is missing"),
    ("bad_stop", {"stop": {"env_steps": 0}}, r"stop\.env_steps: Input should be greater than 0"),
    (
        "bad_resources",
        {"resources": {"num_env_runners": -1}},
        r"resources\.num_env_runners: Input should be greater than or equal to 0",
    ),
    (  # each one a placement-group bundle: refused before a list of 2**32 of them is built
        "too_many_env_runners",
        {"resources": {"num_env_runners": 2**32}},
        r"resources\.num_env_runners: Input should be less than or equal to 4096",
    ),
    (
        "too_many_learners",
        {"resources": {"num_learners": 10**6}},
        r"resources\.num_learners: Input should be less than or equal to 4096",
    ),
    (  # sizes from a typo are refused at load, not by an allocation inside the trial
        "huge_gru_width",
        {"plugins": [], "algorithms": {"mappo": {"gru_hidden": 10**9}}},
        r"algorithms\.mappo\.gru_hidden: Input should be less than or equal to 8192",
    ),
    (
        "huge_replay",
        {"plugins": [], "algorithms": {"qmix": {"buffer_size_episodes": 10**7}}},
        r"algorithms\.qmix\.buffer_size_episodes: Input should be less than or equal to 100000",
    ),
    (
        "zero_width_critic_layer",
        {"plugins": [], "algorithms": {"coma": {"critic_hidden": [64, 0]}}},
        r"algorithms\.coma\.critic_hidden\.1: Input should be greater than or equal to 1",
    ),
    (
        "vdn_hypernetwork_width",
        {"plugins": [], "algorithms": {"vdn": {"hypernet_embed_dim": 8}}},
        r"algorithms\.vdn: hypernet_embed_dim: unused by VDN \(it mixes by a sum, no hypernetworks\); leave it out",
    ),
    (
        "huge_torch_threads",
        {"resources": {"torch_threads": 10**6}},
        r"resources\.torch_threads: Input should be less than or equal to 1024",
    ),
    ("unknown_baseline", {"baselines": ["random", "oracle"]}, r"baselines\.1: unknown baseline 'oracle'"),
    (
        "baseline_scenario_mismatch",
        {"baselines": ["optimal"], "n_uavs": [4]},
        r"baselines\.0: 'optimal' \(with n_eds=5, n_uavs=4\)",
    ),
    (
        "entry_build_check",
        {"algorithms": {"stock_ppo": {"train_batch_size": 10, "minibatch_size": 50}}},
        r"algorithms\.stock_ppo\.minibatch_size: 50 is larger than the train batch \(10\) \(with n_eds=5, n_uavs=1\)",
    ),
    (
        "file_store_uri",
        {"mlflow": {"tracking_uri": "file:./mlruns"}},
        r"mlflow\.tracking_uri: must be a database or server URI",
    ),
    (
        "bad_evaluation",
        {"evaluation": {"episodes": 0}},
        r"evaluation\.episodes: Input should be greater than or equal to 1",
    ),
    ("bad_plugin", {"plugins": ["no_such_module_xyz"]}, r"plugins\.0: cannot import module 'no_such_module_xyz'"),
    (
        "yaml_syntax",
        "experiment: g\nalgorithms: {stock_ppo: null\nseeds: [0]\n",
        r"line 3, column \d+: YAML syntax error",
    ),
    # strict numbers: no bool or string for a number, no NaN or inf (issue 15)
    (
        "bool_for_float",
        {"algorithms": {"stock_ppo": {"lr": True}}},
        r"algorithms\.stock_ppo\.lr: expected a number in \(0, 1\], got True \(bool\)",
    ),
    (
        "inf_for_float",
        {"algorithms": {"stock_ppo": {"lr": float("inf")}}},
        r"algorithms\.stock_ppo\.lr: expected a finite number",
    ),
    (
        "string_for_int",
        {"checkpoint_every": "5"},
        r"checkpoint_every: expected an integer in \[1, 1e\+09\], got '5' \(str\)",
    ),
    ("bool_seed", {"seeds": [True]}, r"seeds\.0: expected an integer in \[0, 4\.29497e\+09\], got True"),
    ("negative_seed", {"seeds": [-1]}, r"seeds\.0: Input should be greater than or equal to 0"),
    ("huge_seed", {"seeds": [2**64]}, r"seeds\.0: expected an integer in \[0, 4\.29497e\+09\] within the 64-bit range"),
    ("seed_above_32_bits", {"seeds": [2**32]}, r"seeds\.0: Input should be less than or equal to 4294967295"),
    (
        "nan_reward_weight",
        {"scenario": {"reward": {"w1": float("nan")}}},
        r"scenario\.reward\.w1: expected a finite number in \[-1e\+06, 1e\+06\], got nan",
    ),
    (
        "nan_mobility",
        {"scenario": {"mobility": {"mean_velocity_init_mps": float("nan")}}},
        r"scenario\.mobility\.mean_velocity_init_mps: expected a finite number",
    ),
    (
        "inf_area",
        {"scenario": {"area_m": float("inf")}},
        r"scenario\.area_m: expected a finite number in \[1, 1e\+07\]",
    ),
    (
        "huge_altitude",
        {"scenario": {"altitude_m": 1e300}},
        r"scenario\.altitude_m: Input should be less than or equal to 10000",
    ),
    (
        "huge_range",
        {"scenario": {"comm_range_m": 1e300}},
        r"scenario\.comm_range_m: Input should be less than or equal to",
    ),
    (
        "tiny_noise",
        {"scenario": {"noise_dbm": -1e6}},
        r"scenario\.noise_dbm: Input should be greater than or equal to -200",
    ),
    (
        "huge_weight",
        {"scenario": {"reward": {"w4": -1e308}}},
        r"scenario\.reward\.w4: Input should be greater than or equal to -1000000",
    ),
    ("bool_in_tuple", {"scenario": {"tp_dbm": [2.0, True]}}, r"scenario\.tp_dbm\.1: expected a number, got True"),
    ("bool_resources", {"resources": {"num_env_runners": True}}, r"resources\.num_env_runners: expected an integer"),
    # names, URIs, storage
    ("escaping_experiment", {"experiment": "../escaped"}, r"experiment: must be 1-64 characters .* without '\.\.'"),
    ("dotdot_experiment", {"experiment": ".."}, r"experiment: must be 1-64 characters"),
    ("slash_experiment", {"experiment": "a/b"}, r"experiment: must be 1-64 characters"),
    ("newline_experiment", {"experiment": "a\nb"}, r"experiment: must be 1-64 characters"),
    ("blank_experiment", {"experiment": " "}, r"experiment: must be 1-64 characters"),
    (
        "bogus_uri",
        {"mlflow": {"tracking_uri": "bogus://x"}},
        r"mlflow\.tracking_uri: must be a database or server URI with scheme one of \['sqlite'",
    ),
    ("http_without_host", {"mlflow": {"tracking_uri": "http://"}}, r"mlflow\.tracking_uri: .*no host"),
    (
        "sqlite_under_a_file",
        {"mlflow": {"tracking_uri": "sqlite:////dev/null/x.db"}},
        r"mlflow\.tracking_uri: the sqlite file's directory is not usable",
    ),
    (
        "storage_under_a_file",
        {"storage": "/dev/null/x"},
        r"storage: must be a directory that exists or can be created: cannot create /dev/null/x: /dev/null is not a directory",
    ),
    (  # a real write test: os.access says yes to root, /proc included
        "sqlite_under_proc",
        {"mlflow": {"tracking_uri": "sqlite:////proc/x/m.db"}},
        r"mlflow\.tracking_uri: the sqlite file's directory is not usable \(cannot create /proc/x: /proc is not writable",
    ),
    (
        "sqlite_in_memory",
        {"mlflow": {"tracking_uri": "sqlite:///:memory:"}},
        r"mlflow\.tracking_uri: a grid's runs must outlive the driver: name a sqlite file",
    ),
    ("storage_under_proc", {"storage": "/proc/x"}, r"storage: .*cannot create /proc/x: /proc is not writable"),
    ("storage_unknown_scheme", {"storage": "ftp://host/x"}, r"storage: must be a local directory or a URI .*'s3'"),
    (
        "plugin_not_a_module_name",
        {"plugins": ["tune_stock_ppo", "a-b"]},
        r"plugins: entry 1: must be a dotted Python module name",
    ),
    # cross-field checks of an algorithm's hyperparameters
    (
        "qmix_learning_starts_above_buffer",
        {
            "plugins": [],
            "algorithms": {
                "qmix": {"buffer_size_episodes": 4, "batch_size_episodes": 2, "learning_starts_episodes": 8}
            },
        },
        r"algorithms\.qmix: learning_starts_episodes \(8\) must be <= buffer_size_episodes \(4\)",
    ),
    (
        "qmix_batch_above_buffer",
        {
            "plugins": [],
            "algorithms": {
                "qmix": {"buffer_size_episodes": 4, "batch_size_episodes": 8, "learning_starts_episodes": 2}
            },
        },
        r"algorithms\.qmix: batch_size_episodes \(8\) must be <= buffer_size_episodes \(4\)",
    ),
    (
        "duplicate_key",
        "experiment: g\nexperiment: h\n",
        r"line 2, column 1: YAML error: duplicate key 'experiment' \(first given on line 1\)",
    ),
    (
        "duplicate_nested_key",
        "experiment: g\nalgorithms:\n  stock_ppo: {lr: 0.1, lr: 0.2}\n",
        r"line 3, column \d+: YAML error: duplicate key 'lr'",
    ),
    ("not_a_mapping", "- just\n- a list\n", r"<top level>: expected a mapping"),
    ("int_key", "experiment: g\n5: 1\n", r"<top level>: 5 is not a field name; allowed: algorithms, baselines"),
]


@pytest.mark.parametrize("case_id,change,pattern", BAD, ids=[b[0] for b in BAD])
def test_bad_grid_names_the_yaml_path(tmp_path, capsys, case_id, change, pattern):
    import ray

    data = change if isinstance(change, str) else _mutate(tmp_path, **change)
    path = write(tmp_path, data)
    with pytest.raises(ConfigError) as info:
        load_grid(path)
    msg = str(info.value)
    assert msg.startswith(f"{path}: "), msg
    assert re.search(pattern, msg[len(path) + 2 :]), msg

    # the CLI: one line on stderr, exit 2, nothing started or written
    rc, out, err = run_cli([path], capsys)
    assert rc == 2
    assert err.strip().count("\n") == 0 and err.startswith("error: ") and "Traceback" not in err
    assert re.search(pattern, err), err
    assert not ray.is_initialized()
    assert not (tmp_path / "ray_results").exists()
    assert not (tmp_path / "mlflow.db").exists()


def test_not_utf8(tmp_path, capsys):
    path = tmp_path / "grid.yaml"
    path.write_bytes(yaml.safe_dump(base_grid(tmp_path)).encode("utf-8") + b"# caf\xe9\n")  # latin-1
    rc, out, err = run_cli([str(path)], capsys)
    assert rc == 2 and out == ""
    assert err.count("\n") == 1 and "is not UTF-8 text (byte 0xe9 at offset" in err and "Traceback" not in err


PLUGIN_FAILURES = [
    (
        "syntax",
        "def broken(:\n",
        r"importing plugin module 'bad_plugin_syntax' failed: SyntaxError \(.*bad_plugin_syntax\.py, line 1\)",
    ),
    (
        "raises",
        "raise RuntimeError('no GPU here')\n",
        r"importing plugin module 'bad_plugin_raises' failed: RuntimeError: no GPU here",
    ),
    ("exits", "import sys\nsys.exit(0)\n", r"importing plugin module 'bad_plugin_exits' failed: SystemExit: 0"),
    (
        "missing_dep",
        "import no_such_dependency_xyz\n",
        r"cannot import module 'bad_plugin_missing_dep': No module named 'no_such_dependency_xyz'",
    ),
]


@pytest.mark.parametrize("kind,source,pattern", PLUGIN_FAILURES, ids=[p[0] for p in PLUGIN_FAILURES])
def test_plugin_import_failures_are_one_line(tmp_path, capsys, monkeypatch, kind, source, pattern):
    name = f"bad_plugin_{kind}"
    (tmp_path / f"{name}.py").write_text(source)
    monkeypatch.syspath_prepend(str(tmp_path))
    rc, out, err = run_cli([write(tmp_path, _mutate(tmp_path, plugins=["tune_stock_ppo", name])), "--dry-run"], capsys)
    assert rc == 2 and out == "", out
    assert err.count("\n") == 1 and err.startswith("error: ") and "plugins.1: " in err, err
    assert re.search(pattern, err), err


def test_resources_beyond_the_local_machine(tmp_path, capsys):
    data = _mutate(tmp_path, resources={"num_cpus_per_learner": 1000})
    path = write(tmp_path, data)
    load_grid(path)  # a valid grid in itself: a cluster may have 1000 CPUs ...
    rc, _, err = run_cli([path], capsys)  # ... the local Ray has not: refused before Ray starts
    assert rc == 2 and re.search(
        r"resources\.num_cpus_per_learner: one trial needs 1000 CPUs .* local Ray has \d+", err
    ), err
    rc, out, err = run_cli([path, "--dry-run"], capsys)  # a preview (of a cluster grid) only notes it
    assert rc == 0 and re.search(r"note: a local run would be refused: .*one trial needs 1000 CPUs", out), out
    rc, out, err = run_cli([path, "--dry-run", "--num-cpus", "2000"], capsys)
    assert rc == 0 and "note:" not in out, err
    data = _mutate(tmp_path, resources={"num_env_runners": 3, "num_cpus_per_env_runner": 1})
    rc, _, err = run_cli([write(tmp_path, data), "--num-cpus", "2"], capsys)
    assert rc == 2 and err.startswith("error: ") and ": resources: one trial needs 4 CPUs" in err, err
    data = _mutate(tmp_path, resources={"num_learners": 4})  # remote learners count too, beside the trial's process
    rc, _, err = run_cli([write(tmp_path, data), "--num-cpus", "2"], capsys)
    assert rc == 2 and "one trial needs 5 CPUs (its own process 1 + num_learners 4 x num_cpus_per_learner 1)" in err, (
        err
    )


def test_storage_flag_is_checked(tmp_path, capsys):
    rc, _, err = run_cli([write(tmp_path, base_grid(tmp_path)), "--dry-run", "--storage", "/dev/null/x"], capsys)
    assert rc == 2 and "--storage" in err and "/dev/null is not a directory" in err


def test_missing_file(tmp_path, capsys):
    rc, _, err = run_cli([str(tmp_path / "nope.yaml")], capsys)
    assert rc == 2 and "cannot read the grid file" in err


@pytest.mark.parametrize(
    "argv, message",
    [
        (["GRID", "--address", " "], "error: --address: empty; allowed: auto, HOST:PORT or ray://HOST:10001"),
        (["", "--dry-run"], "error: grid: empty path; give a grid YAML file"),
        (["GRID", "--dry-run", "--resume"], "error: --dry-run: previews the grid and starts nothing, so --resume"),
    ],
)
def test_flags_that_would_be_ignored_are_refused(tmp_path, capsys, argv, message):
    grid = write(tmp_path, base_grid(tmp_path))
    rc, out, err = run_cli([grid if a == "GRID" else a for a in argv], capsys)
    assert rc == 2 and out == "" and err.strip().startswith(message) and err.count("\n") == 1, err


def test_bad_cli_flag(tmp_path, capsys):
    rc, _, err = run_cli([write(tmp_path, base_grid(tmp_path)), "--num-cpus", "0"], capsys)
    assert rc == 2 and err.startswith("error: ") and "--num-cpus" in err


def test_bad_grid_subprocess_no_traceback(tmp_path):
    path = write(tmp_path, _mutate(tmp_path, algorithms={"stock_ppo": {"lr": -1}}))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([TESTS_DIR, REPO, os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.run(
        [sys.executable, "-m", "uavlora_rllib.tune", path],
        capture_output=True,
        text=True,
        env=env,
        cwd=tmp_path,
        timeout=120,
    )
    assert proc.returncode == 2
    assert proc.stderr.strip() == f"error: {path}: algorithms.stock_ppo.lr: Input should be greater than 0 (got -1)"
    assert proc.stdout == ""
    assert not (tmp_path / "ray_results").exists() and not (tmp_path / "mlflow.db").exists()


# --------------------------------------------------------------------------- dry run
def test_dry_run_prints_one_row_per_trial(tmp_path, capsys):
    import ray

    path = write(tmp_path, base_grid(tmp_path))
    rc, out, err = run_cli([path, "--dry-run"], capsys)
    assert rc == 0, err
    trial_rows = [ln for ln in out.splitlines() if re.match(r"^\s*\d+\s+stock_ppo(_b)?\s", ln)]
    assert len(trial_rows) == 2 * 3 * 2 * 2
    assert len(set(trial_rows)) == len(trial_rows)
    fields = {tuple(ln.split()[1:]) for ln in trial_rows}
    assert ("stock_ppo", "2021", "10", "2", "1000") in fields  # algorithm seed n_eds n_uavs budget
    base_rows = [ln for ln in out.splitlines() if re.match(r"^\s*\d+\s+(random|greedy)\s", ln)]
    assert len(base_rows) == 2 * 3 * 2 * 2
    assert "24 trials" in out and "24 baseline evaluations" in out
    assert "scenario off the paper's defaults: episode_len=10\n" in out  # what makes it not the paper's scenario
    assert not ray.is_initialized()
    assert not (tmp_path / "ray_results").exists() and not (tmp_path / "mlflow.db").exists()


def test_shipped_grids_are_valid():
    """Every YAML in tune_configs/ loads (algorithms still to come are commented out there)."""
    folder = os.path.join(REPO, "tune_configs")
    names = sorted(n for n in os.listdir(folder) if n.endswith(".yaml"))
    assert {
        "smoke.yaml",
        "paper_fig3a.yaml",
        "paper_fig3b.yaml",
        "paper_fig3c.yaml",
        "sweep_mappo_asha.yaml",
        "sweep_qmix_optuna.yaml",
    } <= set(names)  # sweeps: test_sweep.py
    for name in names:
        grid = load_grid(os.path.join(folder, name))
        assert trials(grid)
    fig3b = load_grid(os.path.join(folder, "paper_fig3b.yaml"))
    assert fig3b.n_eds == [10, 20, 40, 60, 80, 100] and fig3b.n_uavs == [2] and fig3b.seeds == [0, 42, 2021]
    fig3c = load_grid(os.path.join(folder, "paper_fig3c.yaml"))
    assert fig3c.n_eds == [60] and fig3c.n_uavs == [2, 4, 6, 8]
    fig3a = load_grid(os.path.join(folder, "paper_fig3a.yaml"))
    assert fig3a.stop.env_steps == 2_000_000 and fig3a.n_eds == [10] and fig3a.n_uavs == [2]
    # the same figures at the converged budget, split so that no scenario runs twice (3b's V=10 is 3a's
    # scenario, 3c's U=2 is one of 3b's; 3b and 3c are one experiment per V or U, to fit a session): together they cover
    # every scenario of the full grids once, with no experiment name twice
    names = [
        "paper_fig3a_3seeds.yaml",
        *(f"paper_fig3b_v{v}.yaml" for v in (20, 40, 60, 80, 100)),
        *(f"paper_fig3c_u{u}.yaml" for u in (4, 6, 8)),
    ]
    fits = {f: load_grid(os.path.join(folder, f)) for f in names}
    assert len({g.experiment for g in fits.values()}) == len(fits)
    cover = [(v, u) for g in fits.values() for v in g.n_eds for u in g.n_uavs]
    full = {(v, u) for g in (fig3a, fig3b, fig3c) for v in g.n_eds for u in g.n_uavs}
    assert len(cover) == len(set(cover)) and set(cover) == full
    for fit in fits.values():
        assert fit.seeds == [0, 1, 2] and fit.stop.env_steps == 200_000 and fit.scenario.get("action_mode") == "per_uav"
        assert set(fit.algorithms) == {"mappo", "ippo", "vdn", "qmix", "coma"} and "best_fixed" in fit.baselines
        assert (fit.evaluation.episodes, fit.evaluation.interval_env_steps) == (10, 20_000)


# The per_device benchmark in one grid per scenario, and the experiments that measured each learner's form there
# (BENCHMARKS.md "per_device learning benchmark"): the one-command grids must run what was measured.
_MEASURED = {
    "10x2": {
        "mappo": ["learning_per_device_10x2_lora_phy"],
        "ippo": ["learning_per_device_10x2_lora_phy"],
        "qmix": ["learning_per_device_10x2_lora_phy_qmix_lr_end"],
        "vdn": ["learning_per_device_10x2_lora_phy_vdn_lr_end"],
        "coma": ["learning_per_device_10x2_lora_phy_coma_return"],
    },
    "60x4": {
        "mappo": ["learning_per_device_60x4_lora_phy", "learning_per_device_60x4_lora_phy_seeds12"],
        "ippo": ["learning_per_device_60x4_lora_phy_ac"],
        "qmix": ["learning_per_device_60x4_lora_phy_qmix_upd4"],
        "vdn": ["learning_per_device_60x4_lora_phy_value_lr_end"],
        "coma": ["learning_per_device_60x4_lora_phy_coma_return"],
    },
    "60x8": {
        "mappo": ["learning_per_device_60x8_lora_phy", "learning_per_device_60x8_lora_phy_seeds12"],
        "ippo": ["learning_per_device_60x8_lora_phy_ippo_value"],
        "qmix": ["learning_per_device_60x8_lora_phy_qmix_upd4"],
        "vdn": ["learning_per_device_60x8_lora_phy_vdn_lr_end"],
        "coma": ["learning_per_device_60x8_lora_phy_coma_return"],
    },
}


def _trial_settings(grid, learner: str) -> tuple:
    """What a learner's trials of `grid` run, validated as the trials are built (defaults filled in): the
    hyperparameters with each single-value grid_search (how a measured grid names its variant) applied, and the
    scenario. More than one value per field fails the unpacking: a benchmark form is one setting."""
    specs = [s for s in trials(grid) if s.algorithm == learner]
    (combo,) = {tuple(c.items()) for s in specs for c in sweep.representative_combinations(s.spaces)}
    (settings,) = {(dataclasses.replace(s.hparams, **dict(combo)), s.scenario) for s in specs}
    return settings


@pytest.mark.parametrize("scenario", sorted(_MEASURED))
def test_benchmark_grids_run_what_was_measured(scenario):
    """tune_configs/benchmark_per_device_<V>x<U>.yaml holds all five learners with the settings, scenario, budget
    and evaluation of the experiments whose results BENCHMARKS.md reports for them (archived beside the report), and the
    three references."""
    folder = os.path.join(REPO, "tune_configs")
    bench = load_grid(os.path.join(folder, f"benchmark_per_device_{scenario}.yaml"))
    assert set(bench.algorithms) == {"mappo", "ippo", "qmix", "vdn", "coma"}
    assert set(bench.baselines) == {"random", "best_fixed", "greedy"}
    assert bench.scenario == {"action_mode": "per_device", "rate_model": "lora_phy"}
    for learner, sources in _MEASURED[scenario].items():
        measured_seeds: set[int] = set()  # the first V=60 grids listed 0-2 but were stopped after seed 0
        for name in sources:
            grid = load_grid(os.path.join(folder, f"{name}.yaml"))
            assert grid.experiment == name
            archive = os.path.join(
                REPO, "docs", "results", "learning_per_device_lora_phy", "runs", f"{name}.mlflow.json.gz"
            )
            assert os.path.isfile(archive), f"{name}: its runs are not archived beside the report"
            assert _trial_settings(grid, learner) == _trial_settings(bench, learner), (learner, name)
            assert (grid.stop, grid.evaluation) == (bench.stop, bench.evaluation), (learner, name)
            measured_seeds |= set(grid.seeds)
        assert measured_seeds == set(bench.seeds), learner


def test_parse_grid_without_file(tmp_path):
    with pytest.raises(ConfigError, match=r"^stop: required field is missing$"):
        parse_grid(_mutate(tmp_path, stop=None))
