"""The package's learner base, common/learner.py (docs/model.md#the-learner).

Every built-in learner derives from `UavLoraLearner` and steps Adam with torch's fused step. Its
`apply_gradients` decides finiteness with one fused max-norm; the parameters and Adam's state it
leaves must be exactly those of RLlib's `TorchLearner.apply_gradients`: for finite gradients on
its own path, and for NaN/inf gradients through RLlib's (which zeroes them).
"""

from __future__ import annotations

import copy
import math

import pytest
import torch
from ray.rllib.core import DEFAULT_MODULE_ID
from ray.rllib.core.learner.torch.torch_learner import TorchLearner

from uavlora_rllib.algorithms.common import registry
from uavlora_rllib.algorithms.common.learner import UavLoraLearner, all_finite
from uavlora_rllib.envs.team import team_action_space, team_observation_space
from uavlora_rllib.sim.scenario import ScenarioConfig

TINY = ScenarioConfig(n_eds=10, n_uavs=2, episode_len=10)


def _learner(name: str) -> UavLoraLearner:
    """The algorithm's learner, built in this process without Ray."""
    entry = registry.get(name)
    config = entry.algorithm_config(TINY, entry.hparams({}), registry.Resources(), 0)
    spaces = {DEFAULT_MODULE_ID: (team_observation_space(TINY), team_action_space(TINY))}
    learner = config.build_learner(env=None, spaces=spaces)
    learner.build()
    return learner


def _optimizers(learner: UavLoraLearner) -> list[torch.optim.Optimizer]:
    return [opt for mid in learner.module.keys() for _, opt in learner.get_optimizers_for_module(mid)]


def _snapshot(learner: UavLoraLearner) -> list[torch.Tensor]:
    """Every parameter and every tensor of every optimizer's state, in a fixed order."""
    out = [p.detach().clone() for p in learner.module[DEFAULT_MODULE_ID].parameters()]
    for opt in _optimizers(learner):
        for p in (p for group in opt.param_groups for p in group["params"]):
            out += [v.detach().clone() for _, v in sorted(opt.state[p].items()) if isinstance(v, torch.Tensor)]
    return out


@pytest.mark.parametrize(
    ("values", "finite"),
    [
        ([1.0, -2.0], True),
        ([3e38, 3e38], True),  # finite, although the 2-norm of these overflows
        ([1.0, math.nan], False),
        ([math.inf, 1.0], False),
        ([-math.inf, 1.0], False),
    ],
)
def test_all_finite(values, finite):
    assert all_finite([torch.ones(5), torch.tensor(values)]) is finite


@pytest.mark.parametrize("name", registry.built_in())
def test_every_built_in_learner_steps_fused_adam(name):
    learner = _learner(name)
    assert isinstance(learner, UavLoraLearner)
    optimizers = _optimizers(learner)
    assert optimizers and all(type(o) is torch.optim.Adam and o.defaults["fused"] for o in optimizers)


@pytest.mark.parametrize("bad", [None, math.nan, math.inf])
@pytest.mark.parametrize("name", ["mappo", "coma"])  # one optimizer; two (actor and critic)
def test_apply_gradients_leaves_what_rllib_leaves(name, bad, monkeypatch):
    learner = _learner(name)
    torch.manual_seed(1)
    grads = {pid: torch.randn_like(p) for pid, p in learner._params.items()}
    if bad is not None:
        next(iter(grads.values())).view(-1)[0] = bad
    state = copy.deepcopy(learner.get_state())
    for _ in range(2):  # a second step reads the first one's Adam state
        TorchLearner.apply_gradients(learner, dict(grads))
    theirs = _snapshot(learner)

    learner.set_state(state)
    rllib_calls = []
    original = TorchLearner.apply_gradients
    monkeypatch.setattr(TorchLearner, "apply_gradients", lambda *a: rllib_calls.append(1) or original(*a))
    for _ in range(2):
        learner.apply_gradients(dict(grads))
    ours = _snapshot(learner)

    assert len(rllib_calls) == (0 if bad is None else 2), "finite gradients take the fused path, others RLlib's"
    assert len(ours) == len(theirs) > 0
    for a, b in zip(ours, theirs, strict=True):
        assert torch.equal(a, b)
    assert all(torch.isfinite(p).all() for p in learner.module[DEFAULT_MODULE_ID].parameters())
