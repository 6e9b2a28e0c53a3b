"""bench and bench_train: every expected failure is one line on stderr and exit code 2, before
anything runs (no Ray started, no benchmark timed)."""

from __future__ import annotations

import pytest
import tune_stock_ppo  # noqa: F401  (registers stock_ppo, a per_uav-only plugin)

from uavlora_rllib import bench, bench_train


def _one_line(err: str) -> bool:
    return err.startswith("error: ") and err.count("\n") == 1 and "Traceback" not in err


@pytest.mark.parametrize(
    "argv, message",
    [
        (["nosuch"], "algo: unknown algorithm 'nosuch'; allowed: ["),
        (["mappo", "--iterations", "0"], "--iterations: must be an integer in [1, 100000], got 0"),
        (["mappo", "--n-eds", "x"], "--n-eds: expected an integer, got 'x'"),
        (["mappo", "--seed", "-1"], "--seed: must be an integer in [0, 4294967295], got -1"),
        (["mappo", "--action-mode", "joint"], "--action-mode: invalid choice: 'joint'"),
        # a plugin registered for per_uav only (tests/tune_stock_ppo.py): every learner here acts in both modes
        (
            ["stock_ppo", "--action-mode", "per_device"],
            "--action-mode: algorithm 'stock_ppo' supports action modes ['per_uav']",
        ),
        (
            # the same plugin's own builder and plain PPO learner: bfloat16 would be ignored, so it is refused
            ["stock_ppo", "--learner-precision", "bfloat16"],
            "resources.learner_precision: 'bfloat16' needs a learner built on common/learner.py's UavLoraLearner",
        ),
        (["mappo", "--set", "lr"], "--set: expected key=value, got 'lr'"),
        (["mappo", "--set", "lr=1", "lr=2"], "--set: 'lr' given twice"),
        (["mappo", "--set", "lr=true"], "--set.lr: expected a number in (0, 1], got True (bool)"),
        (["mappo", "--set", "lr=.inf"], "--set.lr: expected a finite number in (0, 1], got inf"),
        (["mappo", "--set", "lr=[1"], "--set: lr: cannot read the value '[1'"),
        (["mappo", "--set", "no_such_knob=1"], "--set.no_such_knob: unknown field"),
        (["mappo", "--n-eds", "20000"], "scenario.n_eds: Input should be less than or equal to 10000"),
        (
            ["mappo", "--env-runners", "50", "--num-cpus", "2"],
            "--env-runners: 50 runners and a learner need 51 CPUs; Ray has 2",
        ),
        (["mappo", "--set", "num_minibatches=1000"], "algorithms.mappo.num_minibatches: 1000 minibatches"),
    ],
)
def test_bench_train_bad_input(capsys, argv, message):
    import ray

    assert bench_train.main(argv) == 2
    err = capsys.readouterr().err
    assert _one_line(err) and message in err, err
    assert not ray.is_initialized()


def test_bench_train_set_reads_values_as_the_grid_does():
    """--set's own help example, lr=3e-4, is a number (PyYAML alone would read it as text)."""
    assert bench_train._parse_set(["lr=3e-4", "share_actor=true", "actor_heads=shared"]) == {
        "lr": 3e-4,
        "share_actor": True,
        "actor_heads": "shared",
    }


@pytest.mark.parametrize(
    "argv, message",
    [
        ([], "the following arguments are required: what"),
        (["nope"], "invalid choice: 'nope'"),
        (["env", "--repeats", "0"], "--repeats: must be an integer in [1, 1000], got 0"),
        (["env", "--repeats", "two"], "--repeats: expected an integer, got 'two'"),
        (
            ["env", "--write", "/no/such/dir/BENCH.md"],
            "--write: cannot write '/no/such/dir/BENCH.md': /no/such/dir is not a directory",
        ),
        (  # a real write test: os.access says yes to root, /proc included
            ["env", "--write", "/proc/BENCH.md"],
            "--write: cannot write '/proc/BENCH.md': /proc is not writable",
        ),
        (["env", "--bogus"], "unrecognized arguments: --bogus"),
    ],
)
def test_bench_bad_input(capsys, tmp_path, argv, message):
    assert bench.main(argv) == 2
    err = capsys.readouterr().err
    assert _one_line(err) and message in err, err


def test_bench_write_must_not_be_a_directory(capsys, tmp_path):
    assert bench.main(["env", "--write", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert _one_line(err) and "is a directory; allowed: a markdown file" in err, err
    binary = tmp_path / "b.md"
    binary.write_bytes(b"\x8a\xff\x00")  # its other sections would be read back before the benchmark ends
    assert bench.main(["env", "--write", str(binary)]) == 2
    err = capsys.readouterr().err
    assert _one_line(err) and "is not UTF-8 text; allowed: a markdown file" in err, err
