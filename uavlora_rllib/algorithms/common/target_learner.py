"""A TorchLearner whose modules keep target networks through RLlib's `TargetNetworkAPI`.

QMIX/VDN (agent network and mixer) and COMA (critic) bootstrap their TD targets from slowly
moving copies of their own networks. The module declares the pairs (online, target); this
learner makes the copies once its modules exist, and moves them when the algorithm's
learner says so (`update_target_networks`, after a gradient update).
"""

from __future__ import annotations

from ray.rllib.core.learner.torch.torch_learner import TorchLearner
from ray.rllib.core.rl_module.apis import TargetNetworkAPI
from ray.rllib.utils.annotations import override
from ray.rllib.utils.torch_utils import update_target_network

from uavlora_rllib.algorithms.common.learner import UavLoraLearner


class TargetNetworkLearner(UavLoraLearner):
    """Makes every module's target networks after the build; moves them on request."""

    @override(TorchLearner)
    def build(self) -> None:
        super().build()
        self.module.foreach_module(
            lambda mid, mod: mod.make_target_networks() if isinstance(mod, TargetNetworkAPI) else None
        )

    def update_target_networks(self, module_id: str, tau: float) -> None:
        """target <- (1 - tau) target + tau online for each of the module's pairs (tau 1: a copy)."""
        for main, target in self.module[module_id].unwrapped().get_target_network_pairs():
            update_target_network(main_net=main, target_net=target, tau=tau)

    @classmethod
    @override(TorchLearner)
    def rl_module_required_apis(cls) -> list[type]:
        return [TargetNetworkAPI]
