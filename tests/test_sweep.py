"""Sweeps from the grid YAML (experiment/sweep.py): search spaces validated field by field, the
scheduler / search algorithm rules, the Tune objects built from them, trial names, the report's
cells; then (slow) the trainable applying a new config on restore, and end-to-end grids whose
MLflow runs hold the values the trials trained with (an Optuna-sampled lr, a PBT-mutated lr)."""

from __future__ import annotations

import glob
import os
import pickle

import pytest
from conftest import TINY_MAPPO
from conftest import run_tune as cli
from conftest import write_grid as write

from uavlora_rllib.config_errors import ConfigError
from uavlora_rllib.experiment import sweep
from uavlora_rllib.experiment.grid import (
    eval_interval,
    is_sweep,
    load_grid,
    parse_grid,
    trial_count,
    trial_run_name,
    trials,
)
from uavlora_rllib.experiment.tuner import trial_config

TESTS_DIR = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(TESTS_DIR)
EPISODE_LEN = 10  # 2 episodes of 10 slots: 20 env steps per training iteration


def sweep_grid(tmp_path, mappo=None, **extra) -> dict:
    return {
        "experiment": "sw",
        "algorithms": {
            "mappo": {**TINY_MAPPO, **(mappo if mappo is not None else {"lr": {"loguniform": [1e-4, 1e-2]}})}
        },
        "seeds": [0],
        "n_eds": [6],
        "n_uavs": [2],
        "scenario": {"episode_len": EPISODE_LEN},
        "stop": {"env_steps": 200},
        "checkpoint_every": 1,
        "evaluation": {"episodes": 1, "interval_env_steps": 40},
        "resources": {"num_env_runners": 0, "num_envs_per_env_runner": 2, "torch_threads": 1},
        "storage": str(tmp_path / "ray_results"),
        "mlflow": {"tracking_uri": f"sqlite:///{tmp_path / 'mlflow.db'}"},
        **extra,
    }


# --------------------------------------------------------------------------- valid sweeps
def test_search_spaces_expand_with_num_samples_and_grid_search(tmp_path, capsys):
    data = sweep_grid(
        tmp_path,
        {
            "lr": {"loguniform": [1e-4, 1e-2]},
            "entropy_coeff": {"choice": [0.0, 0.01]},
            "num_epochs": {"randint": [1, 4]},
            "share_actor": {"grid_search": [True, False]},
            "critic": {"choice": ["central", "local"]},
        },
        seeds=[0, 1],
        num_samples=3,
    )
    grid = parse_grid(data)
    specs = trials(grid)
    assert len(specs) == 2 and is_sweep(grid, specs)
    assert trial_count(grid, specs) == 2 * 2 * 3  # grid points x grid_search x num_samples
    spaces = specs[0].spaces
    assert spaces["lr"] == sweep.SearchSpace("loguniform", (1e-4, 1e-2))
    assert spaces["num_epochs"].representatives == (1, 3)  # randint: hi exclusive, as Ray Tune's
    assert specs[0].hparams.num_epochs == 15 and specs[0].hparams.batch_episodes == 2  # sampled: default; fixed: set
    rc, out, err = cli([write(tmp_path, data), "--dry-run"], capsys)
    assert rc == 0, err
    assert "sweep: 12 trials = 2 grid points x grid_search values x num_samples 3" in out
    assert "algorithms.mappo.lr: loguniform[0.0001, 0.01]" in out
    assert "algorithms.mappo.share_actor: grid_search[True, False]" in out
    del data["algorithms"]["mappo"]["share_actor"]  # no grid_search space left: the line says so
    rc, out, err = cli([write(tmp_path, data), "--dry-run"], capsys)
    assert rc == 0 and "sweep: 6 trials = 2 grid points x num_samples 3\n" in out, err


def test_the_plain_grid_is_no_sweep(tmp_path):
    grid = parse_grid(sweep_grid(tmp_path, {"lr": 1e-3}, seeds=[0, 1], n_eds=[5, 6]))
    specs = trials(grid)
    assert not is_sweep(grid, specs) and trial_count(grid, specs) == 4
    assert all(not s.spaces for s in specs)


def test_eval_interval_agrees_with_periodic_eval(tmp_path):
    from uavlora_rllib.experiment import periodic_eval

    for interval in (None, 0, 7):
        grid = parse_grid(
            sweep_grid(tmp_path, {"lr": 1e-3}, evaluation={"episodes": 1, "interval_env_steps": interval})
        )
        assert eval_interval(grid) == periodic_eval.resolve_interval(interval, grid.stop.env_steps)


# --------------------------------------------------------------------------- bad sweeps: one line, exit 2
BAD_SPACES = [
    ({"lr": {"loguniform": [0, 1e-3]}}, "algorithms.mappo.lr.loguniform.0: Input should be greater than 0"),
    ({"lr": {"uniform": [1e-3, 2.0]}}, "algorithms.mappo.lr.uniform.1: Input should be less than or equal to 1"),
    ({"lr": {"uniform": [1e-2, 1e-3]}}, "algorithms.mappo.lr.uniform: expected lo < hi"),
    ({"lr": {"uniform": [True, 1e-3]}}, "algorithms.mappo.lr.uniform.0: expected a number in (0, 1], got True"),
    ({"lr": {"uniform": [1e-3]}}, "algorithms.mappo.lr.uniform: expected a list [lo, hi] of two numbers"),
    ({"lr": {"loguniform": 3}}, "algorithms.mappo.lr.loguniform: expected a list [lo, hi]"),
    ({"lr": {"choice": [1e-3, "x"]}}, "algorithms.mappo.lr.choice.1: expected a number in (0, 1], got 'x'"),
    ({"lr": {"choice": []}}, "algorithms.mappo.lr.choice: expected a non-empty list"),
    ({"lr": {"choice": [1e-3, 1e-3]}}, "algorithms.mappo.lr.choice.1: values must be distinct"),
    (
        {"lr": {"normal": [0, 1]}},
        "algorithms.mappo.lr: unknown search space 'normal'; allowed: grid_search, choice, uniform, loguniform, randint",
    ),
    (
        {"lr": {"choice": [1e-3], "uniform": [0.1, 0.2]}},
        "algorithms.mappo.lr: a search space is a mapping with one key",
    ),
    ({"num_epochs": {"uniform": [1, 5]}}, "uniform samples floats and algorithms.mappo.num_epochs is an integer field"),
    (
        {"num_epochs": {"randint": [0, 5]}},
        "algorithms.mappo.num_epochs.randint.0: Input should be greater than or equal to 1",
    ),
    ({"num_epochs": {"randint": [5, 5]}}, "algorithms.mappo.num_epochs.randint: expected lo < hi"),
    (
        {"num_epochs": {"grid_search": [2, 2.5]}},
        "algorithms.mappo.num_epochs.grid_search.1: Input should be a valid integer",
    ),
    (
        {"share_actor": {"randint": [0, 2]}},
        "randint samples integers and algorithms.mappo.share_actor is a true/false field",
    ),
    (
        {"critic": {"grid_search": ["central", "bogus"]}},
        "algorithms.mappo.critic.grid_search.1: Input should be 'central' or 'local'",
    ),
    ({"nope": {"choice": [1]}}, "algorithms.mappo.nope: unknown field; allowed:"),
    # the algorithm's own cross-checks (hyperparameters x scenario), with the sampled value named
    (
        {"actor_agent_heads": {"grid_search": [False, True]}},
        "algorithms.mappo.actor_agent_heads: true needs share_actor: true",
    ),
]


@pytest.mark.parametrize(
    "overrides,message", BAD_SPACES, ids=[m.split(":")[0] + str(i) for i, (_, m) in enumerate(BAD_SPACES)]
)
def test_bad_search_space_is_one_line(tmp_path, capsys, overrides, message):
    rc, out, err = cli([write(tmp_path, sweep_grid(tmp_path, overrides)), "--dry-run"], capsys)
    assert rc == 2 and out == ""
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert message in err, err


def test_sampled_values_are_checked_together(tmp_path):
    """QMIX's own check (epsilon_end <= epsilon_start) over combinations of sampled values."""
    data = sweep_grid(tmp_path)
    data["algorithms"] = {"qmix": {"epsilon_start": {"choice": [0.2, 1.0]}, "epsilon_end": {"choice": [0.05, 0.5]}}}
    with pytest.raises(ConfigError, match=r"epsilon_end \(0.5\) must be <= epsilon_start \(0.2\).*sampled together"):
        parse_grid(data)
    data["algorithms"] = {"qmix": {"epsilon_start": 0.3, "epsilon_end": {"uniform": [0.05, 0.5]}}}
    with pytest.raises(ConfigError, match=r"^algorithms.qmix.*epsilon_end \(0.5\) must be <= epsilon_start \(0.3\)"):
        parse_grid(data)


BAD_SWEEPS = [
    (
        {"scheduler": {"type": "asha"}, "evaluation": {"episodes": 1, "interval_env_steps": 0}},
        "scheduler: needs periodic evaluation of the greedy policy (its metric is eval/ee_sys_mean)",
    ),
    (
        {"search_alg": {"type": "optuna"}, "evaluation": {"episodes": 1, "interval_env_steps": 0}},
        "search_alg: needs periodic evaluation",
    ),
    ({"scheduler": {"type": "hyperband"}}, "scheduler.type: Input should be 'asha', 'pbt' or 'median_stopping'"),
    (
        {"scheduler": {"type": "asha", "perturbation_interval": 40}},
        "scheduler.perturbation_interval: an option of pbt, not of asha",
    ),
    (
        {"scheduler": {"type": "asha", "grace_period": 20}},
        "scheduler.grace_period: 20 env steps is shorter than the periodic evaluation interval (40 env steps",
    ),
    ({"scheduler": {"type": "pbt", "perturbation_interval": 20}}, "scheduler.perturbation_interval: 20 env steps"),
    (
        {"scheduler": {"type": "asha", "reduction_factor": 1}},
        "scheduler.reduction_factor: Input should be greater than 1",
    ),
    ({"scheduler": {"type": "asha"}, "n_eds": [5, 6]}, "n_eds: scheduler asha needs exactly one value here"),
    (
        {"scheduler": {"type": "pbt"}, "algorithms": {"mappo": {"lr": {"uniform": [1e-4, 1e-3]}}, "ippo": None}},
        "algorithms: scheduler pbt needs exactly one value here",
    ),
    (
        {"scheduler": {"type": "pbt"}, "algorithms": {"mappo": {"lr": 1e-3}}},
        "scheduler: pbt mutates the hyperparameters",
    ),
    (
        {"scheduler": {"type": "pbt", "perturbation_factors": [1.2, 0]}},
        "scheduler.perturbation_factors: expected two factors",
    ),
    ({"search_alg": {"type": "hyperopt"}}, "search_alg.type: Input should be 'optuna'"),
    ({"search_alg": {"type": "optuna"}, "seeds": [0, 1]}, "seeds: search_alg optuna needs exactly one value here"),
    (
        {"search_alg": {"type": "optuna"}, "algorithms": {"mappo": {"lr": {"grid_search": [1e-3, 1e-4]}}}},
        "algorithms.mappo.lr.grid_search: optuna cannot sample a grid_search; allowed: choice, uniform, loguniform, randint",
    ),
    (
        {"search_alg": {"type": "optuna"}, "algorithms": {"mappo": {"lr": 1e-3}}},
        "search_alg: optuna needs at least one search space",
    ),
    ({"num_samples": 0}, "num_samples: Input should be greater than or equal to 1"),
    (
        {"scheduler": {"type": "asha"}, "evaluation": {"episodes": 1, "interval_env_steps": 200}},
        "evaluation.interval_env_steps: 200 is not below stop.env_steps (200), so the scheduler never sees",
    ),
    (
        {"num_samples": 5, "algorithms": {"mappo": {"lr": 1e-3}}},
        "num_samples: 5 samples of a grid with no search space are 5 identical trials",
    ),
]


def test_a_search_alg_may_evaluate_only_at_the_end(tmp_path, capsys):
    """Optuna reads a trial's final evaluation, so an interval as long as the budget is a valid search
    (the scheduler's check, which needs the metric during a trial, does not apply)."""
    data = sweep_grid(tmp_path, search_alg={"type": "optuna"}, evaluation={"episodes": 1, "interval_env_steps": 200})
    rc, out, err = cli([write(tmp_path, data), "--dry-run"], capsys)
    assert rc == 0, err


@pytest.mark.parametrize(
    "extra,message", BAD_SWEEPS, ids=[m.split(":")[0] + str(i) for i, (_, m) in enumerate(BAD_SWEEPS)]
)
def test_bad_scheduler_or_search_alg_is_one_line(tmp_path, capsys, extra, message):
    data = sweep_grid(tmp_path, **extra)
    for algo, over in data["algorithms"].items():  # the tiny network wherever one is set
        if isinstance(over, dict) and algo == "mappo":
            data["algorithms"][algo] = {**TINY_MAPPO, **over}
    rc, out, err = cli([write(tmp_path, data), "--dry-run"], capsys)
    assert rc == 2 and out == "", out
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert message in err, err


# --------------------------------------------------------------------------- Tune objects
def test_tune_objects(tmp_path):
    from ray import tune
    from ray.tune.schedulers import ASHAScheduler, MedianStoppingRule, PopulationBasedTraining
    from ray.tune.search.optuna import OptunaSearch

    from uavlora_rllib.experiment.synch_pbt import SynchronousPBT

    spaces = {
        "lr": sweep.SearchSpace("loguniform", (1e-4, 1e-2)),
        "num_epochs": sweep.SearchSpace("randint", (1, 4)),
        "entropy_coeff": sweep.SearchSpace("choice", (0.0, 0.01)),
    }
    assert isinstance(spaces["lr"].to_tune(), tune.search.sample.Float)
    assert spaces["entropy_coeff"].to_mutation() == [0.0, 0.01]
    made = {}
    for kind, extra in (("asha", {}), ("median_stopping", {}), ("pbt", {"perturbation_interval": 80})):
        grid = parse_grid(sweep_grid(tmp_path, {"lr": {"loguniform": [1e-4, 1e-2]}}, scheduler={"type": kind, **extra}))
        made[kind] = sweep.make_scheduler(grid, spaces, eval_interval(grid))
        assert made[kind].metric == sweep.SWEEP_METRIC and made[kind]._mode == "max"
    assert isinstance(made["asha"], ASHAScheduler) and made["asha"]._max_t == 200
    assert [milestone for milestone, _ in made["asha"]._brackets[0]._rungs] == [80]  # grace: 2 x the eval interval
    assert isinstance(made["median_stopping"], MedianStoppingRule)
    pbt = made["pbt"]
    assert isinstance(pbt, PopulationBasedTraining) and pbt._perturbation_interval == 80
    assert not pbt._synch and not isinstance(pbt, SynchronousPBT)
    grid = parse_grid(
        sweep_grid(tmp_path, {"lr": {"loguniform": [1e-4, 1e-2]}}, scheduler={"type": "pbt", "synch": True})
    )
    synch = sweep.make_scheduler(grid, spaces, eval_interval(grid))
    assert isinstance(synch, SynchronousPBT) and synch._synch  # Ray's, less a race (test_synch_pbt.py)
    assert set(pbt._hyperparam_mutations["trial"]["overrides"]) == set(spaces)
    # a perturbed value stays inside its space (x 1.2 of the upper bound, x 0.8 of the lower)
    clamp = pbt._custom_explore_fn
    cfg = clamp({"trial": {"overrides": {"lr": 1.2e-2, "num_epochs": 0, "entropy_coeff": 0.01}}})
    assert cfg["trial"]["overrides"] == {"lr": 1e-2, "num_epochs": 1, "entropy_coeff": 0.01}
    assert isinstance(cfg["trial"]["overrides"]["num_epochs"], int)
    grid = parse_grid(sweep_grid(tmp_path, search_alg={"type": "optuna", "sampler": "random", "seed": 3}))
    searcher = sweep.make_search_alg(grid)
    assert isinstance(searcher, OptunaSearch) and searcher.metric == sweep.SWEEP_METRIC and searcher.mode == "max"
    assert sweep.make_scheduler(parse_grid(sweep_grid(tmp_path)), {}, 40) is None


def test_status_table_shows_the_latest_greedy_evaluation():
    """A finished trial whose last iteration ended no episode has no training EE in its last result;
    its row still shows the latest greedy evaluation, the number the project judges by."""
    from ray.tune.experiment import Trial
    from ray.tune.progress_reporter import _get_trial_info

    from uavlora_rllib.experiment.tuner import status_reporter

    reporter = status_reporter(["lr"])
    trial = Trial(
        "UavLoraTrainable",
        config={"trial": {"algorithm": "mappo", "n_eds": 10, "n_uavs": 2, "seed": 0, "overrides": {"lr": 3e-4}}},
        stub=True,
    )
    trial.update_last_result({"env_steps": 4000, sweep.SWEEP_METRIC: 812.5, "training_iteration": 5})
    trial.set_status(Trial.TERMINATED)
    row = _get_trial_info(trial, list(reporter._parameter_columns), list(reporter._metric_columns))
    assert row[3:] == ["mappo", 10, 2, 0, 3e-4, 4000, 812.5]
    assert reporter._metric_columns[sweep.SWEEP_METRIC] == "greedy EE"


def test_tune_resolves_the_spaces_inside_the_grid(tmp_path):
    """Tune's variant generator samples the spaces nested in the grid's trial dicts, per grid
    point and sample, and each resolved trial config builds its hyperparameters."""
    from ray import tune
    from ray.tune.search.variant_generator import generate_variants

    from uavlora_rllib.algorithms.common import registry

    grid = parse_grid(
        sweep_grid(
            tmp_path,
            {
                "lr": {"loguniform": [1e-4, 1e-2]},
                "num_epochs": {"randint": [1, 4]},
                "share_actor": {"grid_search": [True, False]},
            },
            seeds=[0, 1],
        )
    )
    specs = trials(grid)
    configs = [trial_config(s, grid, True) for s in specs]
    assert configs[0]["sampled"] == ["lr", "num_epochs", "share_actor"] and configs[0]["sweep"] is True
    resolved = [spec["trial"] for _, spec in generate_variants({"trial": tune.grid_search(configs)})]
    assert len(resolved) == 2 * 2
    entry = registry.get("mappo")
    for cfg in resolved:
        hp = entry.hparams(cfg["overrides"])
        assert 1e-4 <= hp.lr <= 1e-2 and 1 <= hp.num_epochs <= 3
        assert sweep.sampled_values(cfg) == {"lr": hp.lr, "num_epochs": hp.num_epochs, "share_actor": hp.share_actor}
    assert {(c["seed"], c["overrides"]["share_actor"]) for c in resolved} == {
        (0, True),
        (0, False),
        (1, True),
        (1, False),
    }


def test_trial_names_are_unique_in_a_sweep():
    cfg = {"algorithm": "mappo", "n_eds": 10, "n_uavs": 2, "seed": 0}
    assert trial_run_name(cfg, "ab12c_00003") == "mappo-V10-U2-s0"  # the plain grid keeps its names
    names = {trial_run_name({**cfg, "sweep": True}, f"ab12c_{i:05d}") for i in range(12)}
    assert len(names) == 12 and "mappo-V10-U2-s0-t00003" in names


def test_report_cells_of_a_sweep():
    """Each sampled configuration is its own cell (its seeds averaged), named with its values."""
    from analysis.data import cell_name, organise
    from analysis.runs import RunRecord

    def rec(i, seed, lr, entropy="0.01"):
        params = {"hparam.lr": lr, "hparam.entropy_coeff": entropy}
        return RunRecord(
            f"r{i}",
            f"mappo-V6-U2-s{seed}-t{i:05d}",
            "FINISHED",
            i,
            "train",
            "mappo",
            str(seed),
            6,
            2,
            params=params,
            metrics={"eval/ee_sys_mean": 100.0 + i},
        )

    records = [rec(0, 0, "0.001"), rec(1, 1, "0.001"), rec(2, 0, "0.000316227766")]
    assert cell_name(records[2]) == "mappo[entropy_coeff=0.01,lr=0.000316]"
    org = organise(records)
    cells = {c.algorithm: c for c in org.cells.values()}
    assert set(cells) == {"mappo[entropy_coeff=0.01,lr=0.001]", "mappo[entropy_coeff=0.01,lr=0.000316]"}
    assert cells["mappo[entropy_coeff=0.01,lr=0.001]"].seeds == ["0", "1"]
    assert not any(c.duplicates for c in cells.values())


EXAMPLES = ("sweep_mappo_asha.yaml", "sweep_qmix_optuna.yaml")


@pytest.mark.parametrize("name", EXAMPLES)
def test_shipped_sweep_examples(name, capsys):
    path = os.path.join(REPO, "tune_configs", name)
    text = open(path).read()
    assert f"python -m uavlora_rllib.tune tune_configs/{name}" in text  # the header names the command
    grid = load_grid(path)
    rc, out, err = cli([path, "--dry-run"], capsys)
    assert rc == 0, err
    assert "metric: eval/ee_sys_mean (max)" in out
    if name.startswith("sweep_mappo"):
        assert grid.scheduler.type == "asha" and set(trials(grid)[0].spaces) == {"lr", "entropy_coeff"}
    else:
        assert grid.search_alg.type == "optuna" and "lr" in trials(grid)[0].spaces
        assert list(grid.algorithms) == ["qmix"]
    # a sweep tunes a learner's benchmark form on the benchmark's scenario: every field it does not search
    # is the benchmark grid's, so its best configuration is comparable with the benchmark's rows
    bench = load_grid(os.path.join(REPO, "tune_configs", "benchmark_per_device_10x2.yaml"))
    assert grid.scenario == bench.scenario and (grid.n_eds, grid.n_uavs) == (bench.n_eds, bench.n_uavs)
    assert {"best_fixed", "greedy"} <= set(grid.baselines)  # the reference and the open-loop constant
    (algo, fields), searched = next(iter(grid.algorithms.items())), set(trials(grid)[0].spaces)
    fixed = {k: v for k, v in fields.items() if k not in searched}
    assert fixed == {k: v for k, v in bench.algorithms[algo].items() if k not in searched}


# --------------------------------------------------------------------------- with Ray (slow)
def _optimizer_lrs(trainable) -> list[float]:
    learner = trainable.algo.learner_group._learner  # num_learners 0: the trial's own process
    return [g["lr"] for opt in learner._named_optimizers.values() for g in opt.param_groups]


@pytest.mark.slow
def test_trainable_trains_with_the_new_config_after_reset_and_restore(ray_address, tmp_path):
    """What PBT's exploit does to a trial: reset_config(mutated config), then restore another
    trial's checkpoint. The optimizer state in the checkpoint holds the old lr; the trial must
    train with its own (mutated) one from the first update on."""
    from uavlora_rllib.experiment.trainable import UavLoraTrainable

    grid = parse_grid(sweep_grid(tmp_path, {"lr": 1e-3}))
    cfg = {**trial_config(trials(grid)[0], grid, True), "sampled": ["lr"]}
    trainable = UavLoraTrainable(config={"trial": cfg})
    try:
        first = trainable.train()
        assert first[f"{sweep.HPARAM_PREFIX}lr"] == 1e-3 and sweep.SWEEP_METRIC in first
        assert first[sweep.SWEEP_METRIC] == first[sweep.METRIC]  # the first iteration is evaluated
        ckpt = str(tmp_path / "ckpt")
        os.makedirs(ckpt)
        trainable.save_checkpoint(ckpt)
        mutated = {**cfg, "overrides": {**cfg["overrides"], "lr": 5e-4}}
        assert trainable.reset_config({"trial": mutated})
        trainable.load_checkpoint(ckpt)
        assert trainable.algo.config.lr == 5e-4 and trainable.algo.config.hparams.lr == 5e-4
        assert _optimizer_lrs(trainable) == [5e-4]  # not the checkpoint's 1e-3
        second = trainable.train()
        assert second[f"{sweep.HPARAM_PREFIX}lr"] == 5e-4
        assert sweep.SWEEP_METRIC in second  # evaluated again after the restore
    finally:
        trainable.stop()


def _runs(tmp_path, experiment):
    from mlflow.tracking import MlflowClient

    client = MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}")
    exp = client.get_experiment_by_name(experiment)
    return client, [r for r in client.search_runs([exp.experiment_id]) if r.data.tags.get("kind") == "train"]


def _checkpoint_lrs(checkpoint: str) -> tuple[float, float, list[float]]:
    """(config.lr, config.hparams.lr, the optimizers' lr) saved in an RLlib checkpoint."""
    import uavlora_rllib.algorithms.mappo.mappo  # noqa: F401  (unpickles MAPPOHParams)

    with open(os.path.join(checkpoint, "class_and_ctor_args.pkl"), "rb") as fh:
        config = pickle.load(fh)["ctor_args_and_kwargs"][0][0]
    with open(os.path.join(checkpoint, "learner_group", "learner", "state.pkl"), "rb") as fh:
        state = pickle.load(fh)
    optim = [g["lr"] for s in state["optimizer"].values() for g in s["state"]["param_groups"]]
    return config["lr"], config["hparams"].lr, optim


def _history(client, run, key):
    return [
        m.value for m in sorted(client.get_metric_history(run.info.run_id, key), key=lambda m: (m.step, m.timestamp))
    ]


@pytest.mark.slow
def test_optuna_sampled_lr_is_logged_as_trained(ray_address, tmp_path, capsys):
    data = sweep_grid(
        tmp_path,
        {"lr": {"loguniform": [1e-4, 1e-2]}},
        experiment="optuna_lr",
        num_samples=2,
        search_alg={"type": "optuna", "sampler": "random", "seed": 0},
        max_concurrent_trials=2,
    )
    data["stop"] = {"env_steps": 40}
    data["evaluation"]["interval_env_steps"] = 20
    rc, out, err = cli([write(tmp_path, data)], capsys)
    assert rc == 0, err[-3000:]
    assert "2/2 trials finished, 0 failed" in out
    client, runs = _runs(tmp_path, "optuna_lr")
    assert len(runs) == 2 and len({r.info.run_name for r in runs}) == 2
    assert len({r.data.params["hparam.lr"] for r in runs}) == 2  # two samples
    for run in runs:
        assert run.info.status == "FINISHED" and run.info.run_name.startswith("mappo-V6-U2-s0-t")
        logged = float(run.data.params["hparam.lr"])
        assert run.data.params["algo.lr"] == run.data.params["hparam.lr"] and 1e-4 <= logged <= 1e-2
        assert set(_history(client, run, "hparam/lr")) == {logged}
        config_lr, hparams_lr, optim = _checkpoint_lrs(run.data.tags["checkpoint"])
        assert config_lr == hparams_lr == logged and optim == [logged]


@pytest.mark.slow
def test_pbt_mutated_lr_is_logged_as_trained(ray_address, tmp_path, capsys):
    data = sweep_grid(
        tmp_path,
        {"lr": {"loguniform": [1e-4, 1e-2]}},
        experiment="pbt_lr",
        num_samples=2,
        max_concurrent_trials=2,
        scheduler={
            "type": "pbt",
            "perturbation_interval": 40,
            "quantile_fraction": 0.5,
            "resample_probability": 0.0,
            "synch": True,
        },
    )
    data["stop"] = {"env_steps": 120}
    rc, out, err = cli([write(tmp_path, data)], capsys)
    assert rc == 0, err[-3000:]
    assert "2/2 trials finished, 0 failed" in out
    client, runs = _runs(tmp_path, "pbt_lr")
    assert len(runs) == 2
    mutated = 0
    for run in runs:
        series = _history(client, run, "hparam/lr")
        assert series[0] == float(run.data.params["hparam.lr"])  # the sampled start
        assert all(1e-4 <= v <= 1e-2 for v in series)  # clamped into the space
        config_lr, hparams_lr, optim = _checkpoint_lrs(run.data.tags["checkpoint"])
        assert config_lr == hparams_lr == series[-1] and optim == [series[-1]]  # what it trained with last
        mutated += len(set(series)) > 1
    assert mutated >= 1  # synchronous PBT, two trials: the lower one exploits the upper at 40 env steps
    assert glob.glob(str(tmp_path / "ray_results" / "pbt_lr" / "*" / "result.json"))
