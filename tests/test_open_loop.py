"""The open-loop check of a policy (experiment.open_loop, evaluate --open-loop): a constant policy is
recognised as one in both action modes, decisions that do not act are left out, and a policy that
reads its observations is told apart from its own modal constant."""

from __future__ import annotations

import json

import numpy as np
import pytest

from uavlora_rllib.baselines import make_baseline
from uavlora_rllib.evaluate import main
from uavlora_rllib.experiment.open_loop import open_loop_check
from uavlora_rllib.sim.scenario import ScenarioConfig

PER_UAV = ScenarioConfig(n_eds=8, n_uavs=2, episode_len=6)
PER_DEVICE = ScenarioConfig(n_eds=12, n_uavs=3, episode_len=6, action_mode="per_device")


@pytest.mark.parametrize("cfg", [PER_UAV, PER_DEVICE], ids=["per_uav", "per_device"])
def test_a_constant_policy_is_its_own_mode(cfg):
    fixed = make_baseline("fixed", cfg)
    check = open_loop_check(fixed, cfg, episodes=3, seed=2)
    assert check.modal_share == 1.0 and check.modal_ee == check.policy_ee and check.modal_ratio == 1.0
    np.testing.assert_array_equal(check.action, fixed._row)


class _ConstantWhereItActs:
    """The fixed action on every component that acts, random values on the ED slots a UAV does not serve."""

    name = "noisy padding"

    def __init__(self, cfg):
        self.fixed, self.cfg, self.rng = make_baseline("fixed", cfg), cfg, np.random.default_rng(0)

    def reset(self, core):
        pass

    def act(self, core):
        a = self.fixed.act(core)
        served = np.stack([(core.serving == u).sum(axis=1) for u in range(self.cfg.n_uavs)], axis=1)
        idle = (np.arange(a.shape[-1] - 1) // 2)[None, None, :] >= served[..., None]
        a[..., :-1] = np.where(idle, self.rng.integers(0, 2, a[..., :-1].shape), a[..., :-1])
        return a


def test_slots_without_an_ed_do_not_count():
    check = open_loop_check(_ConstantWhereItActs(PER_DEVICE), PER_DEVICE, episodes=3, seed=0)
    assert check.modal_share == 1.0 and check.modal_ratio == pytest.approx(1.0)


def test_a_closed_loop_policy_is_told_apart_from_its_mode():
    """per_device greedy picks each ED's SF and TP from its channel: its modal constant earns far less."""
    check = open_loop_check(make_baseline("greedy", PER_DEVICE), PER_DEVICE, episodes=2, seed=0)
    assert check.modal_share < 0.95 and check.modal_ratio < 0.8


def test_cli_open_loop_json_and_text(capsys, tmp_path):
    assert main(["--policy", "fixed", "--episodes", "2", "--n-eds", "6", "--open-loop", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)["open_loop"]
    assert out["modal_share"] == 1.0 and out["modal_ratio"] == 1.0 and len(out["modal_action"]) == 2
    assert out["policy_ee_sys_mean"] == out["modal_ee_sys_mean"]
    assert main(["--policy", "random", "--episodes", "2", "--n-eds", "6", "--open-loop"]) == 0
    line = capsys.readouterr().out.splitlines()[-1]
    assert line.startswith("open-loop check: ") and "of the acting decisions equal the policy's modal action" in line


def test_cli_reports_one_run_of_a_stochastic_policy(capsys):
    """`random` draws from its own RNG: the summary's EE and the check's policy EE are one run's, so
    they agree (a second run, with the RNG advanced and other batches, gave another number)."""
    argv = ["--policy", "random", "--episodes", "5", "--n-eds", "6", "--open-loop", "--json"]
    assert main(argv) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["ee_sys_mean"] == out["open_loop"]["policy_ee_sys_mean"]
