"""`resources.learner_precision: bfloat16` (docs/model.md#learner-precision).

The networks: under the learner's autocast every network's output comes back float32, close to
its float32 output (bfloat16 keeps ~3 significant digits of each product's inputs) but not equal
to it (the products did run in bfloat16). The learners: every built-in algorithm trains one
iteration with it, its update runs under autocast (and only its update: acting stays float32),
and its weights move by finite amounts; with float32 nothing runs under autocast.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from uavlora_rllib.algorithms.common import registry
from uavlora_rllib.algorithms.common.agent_net import RecurrentAgentNet
from uavlora_rllib.algorithms.common.per_ed_actor import PerEDActor
from uavlora_rllib.algorithms.common.precision import autocast_for
from uavlora_rllib.algorithms.mappo.mappo_module import Critic
from uavlora_rllib.algorithms.qmix.branching import BranchingAgentNet
from uavlora_rllib.algorithms.qmix.qmix_module import QMixer
from uavlora_rllib.config_errors import ConfigError, build
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
        scale = ref.abs().max().item()
        err = (x - ref).abs().max().item()
        assert err <= 0.05 * scale, f"{name}: bfloat16 error {err:.3g} against output scale {scale:.3g}"
    assert any(not torch.equal(x, ref) for x, ref in zip(low, reference)), f"{name}: autocast did not run in bfloat16"


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


@pytest.mark.parametrize("precision", ["bfloat16", "float32"])
@pytest.mark.parametrize("name", registry.built_in())  # UavLoraLearners all (test plugins are not)
def test_every_learner_updates_under_its_precision(ray_session, name, precision):
    entry = registry.get(name)
    resources = registry.Resources(num_envs_per_env_runner=4, learner_precision=precision)
    fields = entry.hparams_cls.__pydantic_fields__
    quick = {k: 2 for k in ("batch_size_episodes", "learning_starts_episodes") if k in fields}  # QMIX/VDN learn at once
    algo = entry.build(TINY, entry.hparams(quick), resources, 0).build_algo()
    seen: list[bool] = []  # per module forward in this process: was autocast on?
    hook = torch.nn.modules.module.register_module_forward_hook(
        lambda *_: seen.append(torch.is_autocast_enabled("cpu"))
    )
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
    assert not seen[0], "acting (the first forward of an iteration) must stay float32"
    assert any(seen) == (precision == "bfloat16")


@pytest.mark.parametrize("precision", ["bfloat16", "float32"])
def test_comas_critic_only_steps_run_under_the_trials_precision(precision):
    """COMA's critic-only steps (COMATorchLearner.train_critic, outside RLlib's update) run every forward
    under the trial's learner_precision, as its joint step does."""
    from ray.rllib.core import DEFAULT_MODULE_ID
    from ray.rllib.policy.sample_batch import MultiAgentBatch, SampleBatch

    from uavlora_rllib.algorithms.common.columns import GLOBAL_STATE
    from uavlora_rllib.envs.team import team_action_space, team_observation_space

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
    seen: list[bool] = []
    hook = torch.nn.modules.module.register_module_forward_hook(
        lambda *_: seen.append(torch.is_autocast_enabled("cpu"))
    )
    try:
        learner.train_critic(MultiAgentBatch({DEFAULT_MODULE_ID: SampleBatch(columns)}, 10))
    finally:
        hook.remove()
    assert seen and all(x == (precision == "bfloat16") for x in seen)


@pytest.mark.parametrize("name", registry.built_in())
def test_the_next_forward_reads_the_stepped_weights(name):
    """autocast keeps one bfloat16 copy of each weight for its whole region, and an update steps its
    optimisers several times inside one (minibatches and epochs, COMA's critic-only steps): after the
    learner's apply_gradients, a product with a stepped weight equals the one a fresh region computes."""
    from ray.rllib.core import DEFAULT_MODULE_ID

    from uavlora_rllib.envs.team import team_action_space, team_observation_space

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
