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
from uavlora_rllib.algorithms.common.learner import UavLoraLearner, surely_finite
from uavlora_rllib.envs.team import team_action_space, team_observation_space
from uavlora_rllib.sim.scenario import ScenarioConfig

TINY = ScenarioConfig(n_eds=10, n_uavs=2, episode_len=10)


def _learner(name: str, skip_nan: bool = False) -> UavLoraLearner:
    """The algorithm's learner, built in this process without Ray (`skip_nan`: RLlib's
    torch_skip_nan_gradients)."""
    entry = registry.get(name)
    config = entry.algorithm_config(TINY, entry.hparams({}), registry.Resources(), 0).copy(copy_frozen=False)
    config.torch_skip_nan_gradients = skip_nan
    spaces = {DEFAULT_MODULE_ID: (team_observation_space(TINY), team_action_space(TINY))}
    learner = config.build_learner(env=None, spaces=spaces)
    learner.build()
    return learner


def _fused(opt: torch.optim.Optimizer) -> bool:
    """The flag the step reads: every param group's, not the constructor's defaults."""
    return all(group["fused"] and not group["foreach"] for group in opt.param_groups)


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
        ([1e15, -1e15], True),
        ([3e38, 3e38], False),  # finite, but their 2-norm overflows: RLlib's method then tests them
        ([1.0, math.nan], False),
        ([math.inf, 1.0], False),
        ([-math.inf, 1.0], False),
    ],
)
def test_surely_finite(values, finite):
    assert surely_finite([torch.ones(5), torch.tensor(values), torch.empty(0)]) is finite
    assert surely_finite([torch.empty(0, 3)])


@pytest.mark.parametrize("name", registry.built_in())
def test_every_built_in_learner_steps_fused_adam(name):
    learner = _learner(name)
    assert isinstance(learner, UavLoraLearner)
    optimizers = _optimizers(learner)
    assert optimizers and all(type(o) is torch.optim.Adam and _fused(o) for o in optimizers)


def _apply_twice(learner: UavLoraLearner, grads: dict, method) -> list[torch.Tensor]:
    for _ in range(2):  # a second step reads the first one's Adam state
        method(learner, dict(grads))
    return _snapshot(learner)


@pytest.mark.parametrize("skip_nan", [False, True])
@pytest.mark.parametrize("bad", ["none", "nan", "inf", "stale_nan", "huge"])
@pytest.mark.parametrize("name", ["mappo", "coma"])  # one optimizer; two (actor and critic)
def test_apply_gradients_leaves_what_rllib_leaves(name, bad, skip_nan, monkeypatch):
    """bad: none (every gradient finite), a NaN or inf in one gradient, a NaN in the stale gradient
    of a parameter left out of the dict (RLlib's per-optimizer test reads it), or finite values whose
    2-norm overflows (RLlib's method decides)."""
    learner = _learner(name, skip_nan)
    torch.manual_seed(1)
    grads = {pid: torch.randn_like(p) for pid, p in learner._params.items()}
    first = next(iter(grads))
    if bad in ("nan", "inf", "huge"):
        grads[first].view(-1)[0] = {"nan": math.nan, "inf": math.inf, "huge": 3e38}[bad]
    stale = None
    if bad == "stale_nan":
        stale = grads.pop(first).fill_(math.nan)
    state = copy.deepcopy(learner.get_state())

    def set_stale():
        if stale is not None:
            learner._params[first].grad = stale.clone()

    set_stale()
    theirs = _apply_twice(learner, grads, TorchLearner.apply_gradients)
    learner.set_state(state)
    set_stale()
    rllib_calls = []
    original = TorchLearner.apply_gradients
    monkeypatch.setattr(TorchLearner, "apply_gradients", lambda *a: rllib_calls.append(1) or original(*a))
    ours = _apply_twice(learner, grads, UavLoraLearner.apply_gradients)

    assert len(rllib_calls) == (0 if bad == "none" else 2), "only the case RLlib ends unchanged takes its own path"
    assert len(ours) == len(theirs) > 0
    for a, b in zip(ours, theirs, strict=True):
        assert _same(a, b)


def _same(a: torch.Tensor, b: torch.Tensor) -> bool:
    """Equal, NaN where the other is NaN."""
    return bool(((a == b) | (a.isnan() & b.isnan())).all())


def test_a_missing_gradient_fails_as_in_rllib():
    learner = _learner("mappo")
    grads: dict = {pid: torch.zeros_like(p) for pid, p in learner._params.items()}
    grads[next(iter(grads))] = None
    with pytest.raises(TypeError, match="isfinite"):
        TorchLearner.apply_gradients(learner, dict(grads))
    with pytest.raises(TypeError, match="isfinite"):
        learner.apply_gradients(dict(grads))


def _set_flags(state, **flags) -> int:
    """Set `flags` in every optimizer param group of a learner state; the number of groups changed."""
    if isinstance(state, dict):
        if "param_groups" in state:
            for group in state["param_groups"]:
                group.update(flags)
            return len(state["param_groups"])
        return sum(_set_flags(v, **flags) for v in state.values())
    return 0


@pytest.mark.parametrize("name", ["mappo", "coma"])
def test_a_checkpoint_of_unfused_adam_restores_fused(name):
    """A checkpoint written before Adam was fused (its groups: foreach or the loop) steps fused after
    the restore, to the same numbers as a fused checkpoint."""
    learner = _learner(name)
    torch.manual_seed(2)
    grads = {pid: torch.randn_like(p) for pid, p in learner._params.items()}
    learner.apply_gradients(dict(grads))
    fused_state = copy.deepcopy(learner.get_state())
    old_state = copy.deepcopy(fused_state)
    assert _set_flags(old_state, fused=None, foreach=name == "mappo") > 0

    learner.set_state(fused_state)
    learner.apply_gradients(dict(grads))
    expected = _snapshot(learner)
    learner.set_state(old_state)
    assert all(_fused(o) for o in _optimizers(learner))
    learner.apply_gradients(dict(grads))
    for a, b in zip(_snapshot(learner), expected, strict=True):
        assert torch.equal(a, b)
