"""The batched per-agent network (RecurrentAgentNet, share=False) is U separate networks.

The reference is the loop it replaced: U `_AgentStack`s (nn.Linear, nn.GRU, nn.Linear) run one
after the other on their own agent's rows. Same initial values (the stacked parameters are built
from such networks, in the same order), outputs, final GRU states and gradients (to 1e-5), and
the state_dict keeps the per-agent keys of U separate networks
(docs/model.md#batched-agent-networks).
"""

from __future__ import annotations

import copy

import pytest
import torch
from torch import nn

from uavlora_rllib.algorithms.common.agent_net import RecurrentAgentNet, _AgentStack

TOL = 1e-5


def loop_reference(net: RecurrentAgentNet, out_hidden: int | None) -> nn.ModuleList:
    """U separate networks holding the batched network's per-agent weights."""
    ref = nn.ModuleList(
        _AgentStack(net.in_dim, net.stacked_inp_weight.shape[1], net.gru_hidden, net.n_out, out_hidden)
        for _ in range(net.n_agents)
    )
    ref.load_state_dict({k.removeprefix("nets."): v for k, v in net.state_dict().items()})
    return ref


def loop_forward(ref: nn.ModuleList, obs: torch.Tensor, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The replaced share=False forward: one agent after the other."""
    outs, hs = [], []
    for i, agent in enumerate(ref):
        y, h_i = agent.recurrent(torch.relu(agent.inp(obs[:, :, i])), h[:, i])
        outs.append(agent.out(y))
        hs.append(h_i)
    return torch.stack(outs, dim=2), torch.stack(hs, dim=1)


@pytest.mark.parametrize("out_hidden, out_gain", [(None, None), (6, 0.01)])
@pytest.mark.parametrize("b, t", [(2, 9), (5, 1)])
def test_batched_matches_separate_networks_outputs_and_gradients(out_hidden, out_gain, b, t):
    torch.manual_seed(0)
    u, d = 3, 5
    net = RecurrentAgentNet(d, u, 7, fc_hidden=6, gru_hidden=4, share=False, out_hidden=out_hidden, out_gain=out_gain)
    ref = loop_reference(net, out_hidden)
    obs, h0 = torch.randn(b, t, u, d), torch.randn(b, u, 4)
    out, h_t = net(obs, h0)
    out_ref, h_ref = loop_forward(ref, obs, h0)
    assert out.shape == (b, t, u, 7) and h_t.shape == (b, u, 4)
    torch.testing.assert_close(out, out_ref, atol=TOL, rtol=TOL)
    torch.testing.assert_close(h_t, h_ref, atol=TOL, rtol=TOL)
    w = torch.randn_like(out)  # a loss that weighs every output differently
    ((out * w).sum() + h_t.square().sum()).backward()
    ((out_ref * w).sum() + h_ref.square().sum()).backward()
    for name in net.stacked_names:
        grad = net.get_parameter("stacked_" + name.replace(".", "_")).grad
        for i, agent in enumerate(ref):
            torch.testing.assert_close(grad[i], agent.get_parameter(name).grad, atol=TOL, rtol=TOL, msg=f"{name}[{i}]")


def test_initial_values_are_those_of_separate_networks_built_in_order():
    torch.manual_seed(11)
    net = RecurrentAgentNet(5, 3, 7, fc_hidden=6, gru_hidden=4, share=False, out_hidden=6, out_gain=0.01)
    torch.manual_seed(11)
    ref = nn.ModuleList(_AgentStack(5, 6, 4, 7, 6) for _ in range(3))
    for agent in ref:
        nn.init.orthogonal_(agent.out[-1].weight, gain=0.01)
        nn.init.zeros_(agent.out[-1].bias)
    got = net.state_dict()
    assert list(got) == [f"nets.{k}" for k in ref.state_dict()]  # the keys, in the same order
    for key, value in ref.state_dict().items():
        assert torch.equal(got[f"nets.{key}"], value), key


def test_state_dict_round_trip_and_target_copy():
    torch.manual_seed(1)
    a = RecurrentAgentNet(5, 2, 3, fc_hidden=6, gru_hidden=4, share=False)
    b = RecurrentAgentNet(5, 2, 3, fc_hidden=6, gru_hidden=4, share=False)
    b.load_state_dict(a.state_dict())  # strict: no key missing or left over
    obs, h0 = torch.randn(2, 4, 2, 5), torch.zeros(2, 2, 4)
    assert torch.equal(a(obs, h0)[0], b(obs, h0)[0])
    c = copy.deepcopy(a)  # target networks are deep copies synced through state_dict
    c.load_state_dict({k: 2 * v for k, v in a.state_dict().items()})
    assert torch.equal(c.stacked_inp_weight, 2 * a.stacked_inp_weight)
    assert sorted(n for n, _ in a.named_parameters()) == sorted(n for n, _ in c.named_parameters())
