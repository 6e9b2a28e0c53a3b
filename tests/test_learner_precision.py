"""`resources.learner_precision: bfloat16` (docs/model.md#learner-precision), by both of its routes.

The networks: under either route every network's output comes back float32, close to its float32
output (bfloat16 keeps ~3 significant digits of each product's inputs) but not equal to it where
the products did run in bfloat16 (always under autocast; under oneDNN's route where this CPU's
oneDNN rounds, which a probe product tells). The routes: the probe decides the CPU's, the oneDNN
setting comes back after its context (also after an error). The learners: every built-in
algorithm trains with it by each route, its update runs in it (and only its update: acting stays
float32), and its weights move by finite amounts; with float32 nothing changes.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from uavlora_rllib.algorithms.common import precision as precision_module
from uavlora_rllib.algorithms.common import registry
from uavlora_rllib.algorithms.common.agent_net import RecurrentAgentNet
from uavlora_rllib.algorithms.common.per_ed_actor import PerEDActor
from uavlora_rllib.algorithms.common.precision import autocast_for, onednn_bfloat16, onednn_rounds_in_bfloat16
from uavlora_rllib.algorithms.mappo.mappo_module import Critic
from uavlora_rllib.algorithms.qmix.branching import BranchingAgentNet
from uavlora_rllib.algorithms.qmix.qmix_module import QMixer
from uavlora_rllib.config_errors import ConfigError, build
from uavlora_rllib.experiment.trainable import precision_routes
from uavlora_rllib.sim.observation import OBS_EXTRA, OBS_ROW
from uavlora_rllib.sim.scenario import ScenarioConfig

CPU = torch.device("cpu")
B, T, U, QUOTA, H = 4, 6, 3, 5, 32
OBS_DIM = QUOTA * OBS_ROW + OBS_EXTRA


def _nets() -> dict[str, tuple[torch.nn.Module, tuple[torch.Tensor, ...]]]:
    torch.manual_seed(0)
    obs, h = torch.randn(B, T, U, OBS_DIM), torch.randn(B, U, H)
    kw = {"fc_hidden": H, "gru_hidden": H}
    return {
        "agent_net_stacked": (RecurrentAgentNet(OBS_DIM, U, 11, share=False, out_hidden=H, **kw), (obs, h)),
        "agent_net_shared": (RecurrentAgentNet(OBS_DIM, U, 11, share=True, agent_heads=True, **kw), (obs, h)),
        "per_ed_actor": (
            PerEDActor(OBS_DIM, U, QUOTA, 6, 3, 3, heads="shared", share=False, out_gain=1.0, **kw),
            (obs, h),
        ),
        "branching_q": (
            BranchingAgentNet(
                OBS_DIM, U, QUOTA, 18, 3, head_hidden=H, share=False, slot_head="shared", dueling=True, **kw
            ),
            (obs, h),
        ),
        "central_critic": (Critic(40, H, U, value_norm=False, shared=True), (torch.randn(B, T, 40),)),
        "qmix_mixer": (QMixer(U, 40, embed_dim=8, hypernet_embed=16), (torch.randn(B, T, U), torch.randn(B, T, 40))),
    }


def _tensors(out) -> list[torch.Tensor]:
    return [x for x in (out if isinstance(out, tuple) else (out,)) if isinstance(x, torch.Tensor)]


@pytest.mark.parametrize("name", list(_nets()))
def test_outputs_are_float32_and_close_under_bfloat16_autocast(name):
    net, args = _nets()[name]
    reference = _tensors(net(*args))
    with autocast_for("bfloat16", CPU):
        low = _tensors(net(*args))
    with autocast_for("float32", CPU):
        same = _tensors(net(*args))
    for ref, x, y in zip(reference, low, same, strict=True):
        assert x.dtype == torch.float32 and y.dtype == torch.float32
        torch.testing.assert_close(y, ref, rtol=0, atol=0)  # float32: autocast off, the very same numbers
        _assert_within_bfloat16(name, x, ref)
    assert any(not torch.equal(x, ref) for x, ref in zip(low, reference)), f"{name}: autocast did not run in bfloat16"


@pytest.mark.parametrize("name", list(_nets()))
def test_outputs_are_float32_and_close_under_onednn_bfloat16(name):
    net, args = _nets()[name]
    reference = _tensors(net(*args))
    with onednn_bfloat16():
        low = _tensors(net(*args))
    for ref, x in zip(reference, low, strict=True):
        assert x.dtype == torch.float32
        _assert_within_bfloat16(name, x, ref)
        if not onednn_rounds_in_bfloat16():  # oneDNN's float32 kernels instead of MKL's: float32's own digits
            torch.testing.assert_close(x, ref, rtol=1e-5, atol=1e-5 * ref.abs().max().item())
    if onednn_rounds_in_bfloat16():
        assert any(not torch.equal(x, ref) for x, ref in zip(low, reference)), f"{name}: no product rounded"


def _assert_within_bfloat16(name: str, x: torch.Tensor, ref: torch.Tensor) -> None:
    scale = ref.abs().max().item()
    err = (x - ref).abs().max().item()
    assert err <= 0.05 * scale, f"{name}: bfloat16 error {err:.3g} against output scale {scale:.3g}"


def test_the_onednn_setting_comes_back_after_its_context():
    start = torch.backends.mkldnn.matmul.fp32_precision
    with onednn_bfloat16():
        assert _onednn_on()
        with onednn_bfloat16():
            assert _onednn_on()
        assert _onednn_on()  # an inner context gives back what it found
    assert torch.backends.mkldnn.matmul.fp32_precision == start
    with pytest.raises(RuntimeError, match="inside"), onednn_bfloat16():
        raise RuntimeError("inside")
    assert torch.backends.mkldnn.matmul.fp32_precision == start


def test_the_route_follows_the_probe():
    """A CPU whose oneDNN rounds takes the oneDNN route, any other CPU and a GPU autocast; float32 takes none."""
    assert precision_module.bfloat16_route(CPU) == ("onednn" if onednn_rounds_in_bfloat16() else "autocast")
    assert precision_module.bfloat16_route(torch.device("cuda")) == "autocast"
    with precision_module.precision_context("float32", CPU):
        assert not _onednn_on() and not torch.is_autocast_enabled("cpu")
    with precision_module.precision_context("bfloat16", CPU):
        assert _onednn_on() != torch.is_autocast_enabled("cpu")  # exactly one route
    assert not _onednn_on() and not torch.is_autocast_enabled("cpu")


@pytest.mark.parametrize("inside_autocast", [False, True])
def test_the_probe_says_no_where_onednn_does_not_round(inside_autocast):
    """oneDNN switched off stands for a CPU whose oneDNN does not round: the answer is no, also for a first
    caller inside an autocast region (whose bfloat16 product would round anywhere)."""
    onednn_rounds_in_bfloat16.cache_clear()
    before, torch.backends.mkldnn.enabled = torch.backends.mkldnn.enabled, False
    try:
        with torch.autocast("cpu", enabled=inside_autocast):
            assert not onednn_rounds_in_bfloat16()
    finally:
        torch.backends.mkldnn.enabled = before
        onednn_rounds_in_bfloat16.cache_clear()


def _onednn_on() -> bool:
    return torch.backends.mkldnn.matmul.fp32_precision == "bf16"


def _route_now() -> str | None:
    """The route this moment's code runs in: 'onednn', 'autocast', None (float32), or 'both' (never right)."""
    on = {"onednn": _onednn_on(), "autocast": torch.is_autocast_enabled("cpu")}
    return "both" if all(on.values()) else next((k for k, v in on.items() if v), None)


def _bfloat16_on() -> bool:
    """Does this moment's code run in bfloat16 by either route?"""
    return _route_now() is not None


ROUTES = [("bfloat16", "onednn"), ("bfloat16", "autocast"), ("float32", None)]


def test_learner_precision_is_checked_at_the_boundary():
    assert build(registry.Resources, {"learner_precision": "bfloat16"}, "resources").learner_precision == "bfloat16"
    with pytest.raises(ConfigError, match=r"resources\.learner_precision.*float32.*bfloat16"):
        build(registry.Resources, {"learner_precision": "fp16"}, "resources")


def test_a_learner_without_precision_is_refused_bfloat16():
    """An algorithm whose learner ignores the setting (a plugin's plain TorchLearner, through `team_config` or
    its own builder) is refused in one line when its trial's config is built, rather than run in float32."""
    import dataclasses

    from ray.rllib.core.learner.torch.torch_learner import TorchLearner

    from uavlora_rllib.algorithms.common.config import team_config
    from uavlora_rllib.algorithms.mappo.mappo import MAPPOConfig

    class PlainLearnerConfig(MAPPOConfig):
        learner_class = TorchLearner

    mappo = registry.get("mappo")
    entry = dataclasses.replace(
        mappo,
        name="plain",
        build=lambda sc, hp, res, seed: team_config(PlainLearnerConfig(), "plain", sc, hp, res, seed),
    )
    bf16 = registry.Resources(learner_precision="bfloat16")
    with pytest.raises(ConfigError, match=r"^resources\.learner_precision: 'bfloat16' needs .*allowed: 'float32'$"):
        entry.algorithm_config(TINY, mappo.hparams({}), bf16, 0)
    entry.algorithm_config(TINY, mappo.hparams({}), registry.Resources(), 0)  # float32: fine
    mappo.algorithm_config(TINY, mappo.hparams({}), bf16, 0)  # a UavLoraLearner: fine


TINY = ScenarioConfig(n_eds=10, n_uavs=2, episode_len=10, action_mode="per_device")


@pytest.mark.parametrize(("precision", "route"), ROUTES)
@pytest.mark.parametrize("name", registry.built_in())  # UavLoraLearners all (test plugins are not)
def test_every_learner_updates_under_its_precision(ray_session, monkeypatch, name, precision, route):
    monkeypatch.setattr(precision_module, "bfloat16_route", lambda device: route)  # the learner learns here
    entry = registry.get(name)
    resources = registry.Resources(num_envs_per_env_runner=4, learner_precision=precision)
    fields = entry.hparams_cls.__pydantic_fields__
    quick = {k: 2 for k in ("batch_size_episodes", "learning_starts_episodes") if k in fields}  # QMIX/VDN learn at once
    algo = entry.build(TINY, entry.hparams(quick), resources, 0).build_algo()
    # what the trial reports and its MLflow run records (run_schema.PRECISION_ROUTE)
    assert precision_routes(algo) == (f"bfloat16/{route}" if route else "float32")
    seen: list[str | None] = []  # per module forward in this process: the route it ran in
    hook = torch.nn.modules.module.register_module_forward_hook(lambda *_: seen.append(_route_now()))
    try:
        from ray.rllib.core import DEFAULT_MODULE_ID

        def weights() -> dict:  # the learner's weights, through the public API
            return algo.learner_group.get_weights([DEFAULT_MODULE_ID])[DEFAULT_MODULE_ID]

        before = weights()
        for _ in range(2):
            algo.train()
        after = weights()
    finally:
        hook.remove()
        algo.stop()
    moved = [float(np.abs(np.asarray(after[k]) - np.asarray(before[k])).max()) for k in before]
    assert all(np.isfinite(moved)) and max(moved) > 0, f"{name}: the update changed no weight"
    assert seen[0] is None, "acting (the first forward of an iteration) must stay float32"
    want = {None, route} if route else {None}  # acting float32, the update in its route, never the other
    assert set(seen) == want, set(seen)
    assert not _bfloat16_on(), "the update must give the process its float32 products back"


@pytest.mark.parametrize(("precision", "route"), ROUTES)
def test_comas_critic_only_steps_run_under_the_trials_precision(monkeypatch, precision, route):
    """COMA's critic-only steps (COMATorchLearner.train_critic, outside RLlib's update) run every forward
    under the trial's learner_precision, as its joint step does."""
    from ray.rllib.core import DEFAULT_MODULE_ID
    from ray.rllib.policy.sample_batch import MultiAgentBatch, SampleBatch

    from uavlora_rllib.algorithms.common.columns import GLOBAL_STATE
    from uavlora_rllib.envs.team import team_action_space, team_observation_space

    monkeypatch.setattr(precision_module, "bfloat16_route", lambda device: route)
    scenario = ScenarioConfig(n_eds=4, n_uavs=2, episode_len=5)
    entry = registry.get("coma")
    hparams = entry.hparams({"actor_hidden": 16, "gru_hidden": 8, "critic_hidden": [32], "critic_steps": 2})
    config = entry.build(scenario, hparams, registry.Resources(learner_precision=precision), 0)
    spaces = {DEFAULT_MODULE_ID: (team_observation_space(scenario), team_action_space(scenario))}
    learner = config.build_learner(env=None, spaces=spaces)
    gen = np.random.default_rng(0)
    obs_dim, state_dim = spaces[DEFAULT_MODULE_ID][0].shape[-1], config.model_config["state_dim"]
    columns = {
        "obs": gen.random((2, 6, 2, obs_dim), dtype=np.float32),
        "actions": gen.integers(0, 90, (2, 5, 2)),
        "rewards": gen.random((2, 5), dtype=np.float32),
        GLOBAL_STATE: gen.standard_normal((2, 6, state_dim), dtype=np.float32),
    }
    seen: list[str | None] = []
    hook = torch.nn.modules.module.register_module_forward_hook(lambda *_: seen.append(_route_now()))
    try:
        learner.train_critic(MultiAgentBatch({DEFAULT_MODULE_ID: SampleBatch(columns)}, 10))
    finally:
        hook.remove()
    assert seen and all(x == route for x in seen), set(seen)


@pytest.mark.parametrize("name", registry.built_in())
def test_the_next_forward_reads_the_stepped_weights(monkeypatch, name):
    """autocast keeps one bfloat16 copy of each weight for its whole region, and an update steps its
    optimisers several times inside one (minibatches and epochs, COMA's critic-only steps): after the
    learner's apply_gradients, a product with a stepped weight equals the one a fresh region computes."""
    from ray.rllib.core import DEFAULT_MODULE_ID

    from uavlora_rllib.envs.team import team_action_space, team_observation_space

    monkeypatch.setattr(precision_module, "bfloat16_route", lambda device: "autocast")  # the route with the copies
    entry = registry.get(name)
    scenario = ScenarioConfig(n_eds=4, n_uavs=2, episode_len=5)
    config = entry.algorithm_config(scenario, entry.hparams({}), registry.Resources(learner_precision="bfloat16"), 0)
    spaces = {DEFAULT_MODULE_ID: (team_observation_space(scenario), team_action_space(scenario))}
    learner = config.build_learner(env=None, spaces=spaces)
    optimizers = [opt for _, opt in learner.get_optimizers_for_module(DEFAULT_MODULE_ID)]
    params = [p for opt in optimizers for group in opt.param_groups for p in group["params"]]
    for opt in optimizers:
        for group in opt.param_groups:
            group["lr"] = 0.5  # a step that moves the weights' bfloat16 values
    weight = next(p for p in params if p.dim() == 2)
    x = torch.randn(3, weight.shape[1])
    with learner.precision():
        before = torch.nn.functional.linear(x, weight)
        learner.apply_gradients({learner.get_param_ref(p): torch.ones_like(p) for p in params})
        after = torch.nn.functional.linear(x, weight)
    with learner.precision():
        fresh = torch.nn.functional.linear(x, weight)
    assert not torch.equal(before, after)
    torch.testing.assert_close(after, fresh, rtol=0, atol=0)


@pytest.mark.parametrize("route", ["onednn", "autocast"])
def test_bench_train_says_which_route_bfloat16_took(monkeypatch, route):
    from uavlora_rllib.bench_train import precision_line

    monkeypatch.setattr(precision_module, "bfloat16_route", lambda device: route)
    assert precision_line("float32") == "learner precision: float32"
    want = "oneDNN's bfloat16 products" if route == "onednn" else "torch.autocast (this CPU's oneDNN does not round)"
    assert precision_line("bfloat16") == f"learner precision: bfloat16 by {want}"
