"""Does COMA's per_device critic know what one ED's SF is worth? (BENCHMARKS.md "per_device", COMA)

At gamma 0 the critic's target is the slot's reward, so Q_{u,l}(s, a)[c] should track the reward of
the joint action with branch l of UAV u set to c, which the simulator gives exactly
(AllocationScorer.score_ed_moves on the same slot). For every served ED's SF branch this compares the critic's
values, centred over the SFs, with those exact rewards, centred: their correlation, and how often
the two pick the same SF (chance 1/6). It also prints the effect size: the std of the team reward
over one ED's SFs, against the reward's own std.

    python docs/history/measurements/coma_critic_probe.py checkpoint PATH V U
        a trained COMA checkpoint, on its own sampled policy's slots (6 scenarios, slots 3-5)
    python docs/history/measurements/coma_critic_probe.py onpolicy PATH V U BATCHES STEPS
        does the trained critic predict the reward of its own policy's slots (R^2 of its taken value on
        2 x 16 held-out episodes), and does a fresh critic, fitted to BATCHES x 16 episodes of that
        policy as `offline` fits, generalise to them
    python docs/history/measurements/coma_critic_probe.py offline STEPS BATCHES
        a fresh critic (COMA's defaults: 128-128, dueling, Adam 5e-4, grad clip 10) regressed on the
        reward of BATCHES x 16 episodes of uniformly random per-ED actions at V=60/U=4, on a random
        1/8 of its rows per step (COMA's critic_branch_fraction of the 60/x grids), 512 slots per
        step; then the same comparison on held-out random slots
"""

import os
import sys

import numpy as np
import torch

from uavlora_rllib.algorithms.coma.branching import BranchQCritic
from uavlora_rllib.algorithms.common.action_head import BranchLayout, taken
from uavlora_rllib.baselines.slots import AllocationScorer, Slots
from uavlora_rllib.envs.team import team_action_space
from uavlora_rllib.sim.core import BatchCore
from uavlora_rllib.sim.scenario import ScenarioConfig

torch.set_num_threads(1)
SCENARIOS = 6


def scenario(v: int, u: int) -> ScenarioConfig:
    return ScenarioConfig(n_eds=v, n_uavs=u, action_mode="per_device", rate_model="lora_phy")


def exact_sf_rewards(core: BatchCore, a: np.ndarray) -> np.ndarray:
    """The slot's reward with each ED moved to each SF at its own TP, the others held [N, V, n_sf]
    (baselines/slots.py AllocationScorer.score_ed_moves: the simulator's equations, vectorised)."""
    cfg, slots = core.cfg, Slots.of_core(core)
    n, v = slots.g_serving.shape
    sf, tp, _ = core.decoder.allocations(a, core.links)  # the simulator's own decoding, per ED
    setting = np.where(slots.associated, sf * cfg.n_tp + tp, 0).astype(np.int64)
    scorer = AllocationScorer(cfg, core.tables, "reward")
    moved, _ = scorer.score_ed_moves(
        setting, a[:, :, -1].astype(np.int64), slots, np.broadcast_to(np.arange(v), (n, v))
    )
    by_sf = moved.reshape(n, v, cfg.n_sf, cfg.n_tp)  # settings are sf * n_tp + tp
    return np.take_along_axis(by_sf, np.where(slots.associated, tp, 0)[..., None, None], axis=-1)[..., 0]


def compare(cfg: ScenarioConfig, critic_values, act, seed: int = 999) -> None:
    """critic_values(core, a) -> Q [N, U, L, W]; act(core) -> a [N, U, L]; slots 3-5 of 6 scenarios."""
    core = BatchCore(cfg, SCENARIOS)
    core.reset(seed)
    corrs, agree, effect, rewards = [], [], [], []
    for t in range(6):
        a = act(core)
        if t >= 3:
            q = critic_values(core, a)  # [N, U, L, W]
            exact = exact_sf_rewards(core, a)  # [N, V, n_sf]
            served = np.argwhere(core.associated)  # (scenario, ED)
            uav, slot = core.links.serving_idx, core.slot_of_ed
            for i, ed in served:
                values = q[i, uav[i, ed], 2 * slot[i, ed], : cfg.n_sf]  # the ED's slot's SF branch
                effect.append(exact[i, ed].std())
                if exact[i, ed].std() > 1e-9:
                    corrs.append(np.corrcoef(exact[i, ed] - exact[i, ed].mean(), values - values.mean())[0, 1])
                    agree.append(exact[i, ed].argmax() == values.argmax())
        rewards.append(core.step(a).reward)
    print(
        f"reward per slot mean {np.mean(rewards):.1f} std {np.std(rewards):.1f}; one ED's SF moves it by "
        f"{np.mean(effect):.2f} (std over its SFs, mean)\ncorrelation of the critic's centred values with the exact "
        f"ones: mean {np.mean(corrs):.3f}, median {np.median(corrs):.3f}; same best SF {np.mean(agree):.3f} "
        f"(chance {1 / cfg.n_sf:.3f}); {len(corrs)} ED branches"
    )


def from_checkpoint(path: str, v: int, u: int) -> None:
    cfg = scenario(v, u)
    policy, module = load(path, cfg)
    started = []

    def act(core):
        if not started:
            policy.reset(core)
            started.append(True)
        return policy.act(core)

    def values(core, a):
        state = torch.as_tensor(core.state(), dtype=torch.float32)
        obs = torch.as_tensor(core.obs, dtype=torch.float32)
        with torch.no_grad():
            return module.critic_q(module.critic, state, obs, torch.as_tensor(a)).numpy()

    compare(cfg, values, act)


def load(path: str, cfg: ScenarioConfig):
    """(sampled policy, learner module with the critic) of a COMA checkpoint."""
    from ray.rllib.algorithms.algorithm import Algorithm

    from uavlora_rllib.algorithms.common.registry import entry_for_algorithm

    algo = Algorithm.from_checkpoint(os.path.abspath(path))
    policy = entry_for_algorithm(algo).policy(algo, cfg, explore=True, seed=1)
    return policy, algo.learner_group._learner.module["default_policy"].unwrapped()


def collect(cfg: ScenarioConfig, act, batches: int, seed: int, reset=None) -> list[torch.Tensor]:
    """state, obs, actions, reward of `batches` rounds of 16 whole episodes played by act(core)."""
    core = BatchCore(cfg, 16)
    core.reset(seed)
    data: list[list[np.ndarray]] = [[], [], [], []]
    for _ in range(batches):
        if reset is not None:
            reset(core)
        for _ in range(cfg.episode_len):
            a = act(core)
            for part, x in zip(data, (core.state().astype(np.float32), core.obs.astype(np.float32), a)):
                part.append(x)
            data[3].append(core.step(a).reward.astype(np.float32))
        core.reset()
    return [torch.as_tensor(np.concatenate(x)) for x in data]


def fit(cfg: ScenarioConfig, data: list[torch.Tensor], steps: int, report=None) -> BranchQCritic:
    """A fresh critic (COMA's defaults) regressed on the slots' rewards, 1/8 of its rows per step."""
    state, obs, actions, reward = data
    nvec = team_action_space(cfg).nvec
    torch.manual_seed(0)
    critic = BranchQCritic(
        BranchLayout(nvec[0].tolist()), nvec.shape[0], state.shape[1], obs.shape[-1], (128, 128), True
    )
    opt = torch.optim.Adam(critic.parameters(), lr=5e-4)
    for step in range(steps):
        idx = torch.randint(0, len(reward), (512,))
        rows = torch.randperm(nvec.size)[: round(0.125 * nvec.size)].sort().values
        q = critic(state[idx], obs[idx], actions[idx], rows)
        loss = ((taken(q, actions[idx].flatten(-2)[:, rows]) - reward[idx, None]) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(critic.parameters(), 10.0)
        opt.step()
        if step % max(1, steps // 4) == 0 or step == steps - 1:
            print(f"step {step}: train MSE {loss.item():.1f}" + (f"; {report(critic)}" if report else ""))
    return critic


def r_squared(critic, data: list[torch.Tensor]) -> float:
    """R^2 of the critic's taken value (mean over its rows) against the slots' rewards."""
    state, obs, actions, reward = data
    with torch.no_grad():
        pred = torch.cat(
            [
                taken(
                    critic(state[i : i + 1200], obs[i : i + 1200], actions[i : i + 1200]), actions[i : i + 1200]
                ).mean((1, 2))
                for i in range(0, len(reward), 1200)
            ]
        )
    return 1.0 - float(((pred - reward) ** 2).mean() / reward.var())


def on_policy(path: str, v: int, u: int, batches: int, steps: int) -> None:
    cfg = scenario(v, u)
    policy, module = load(path, cfg)
    train = collect(cfg, policy.act, batches, 11, reset=policy.reset)
    held_out = collect(cfg, policy.act, 2, 99, reset=policy.reset)
    print(f"{len(train[3])} + {len(held_out[3])} slots; reward std {train[3].std():.1f}")
    print(f"the trained critic on the held-out slots: R^2 {r_squared(module.critic, held_out):.3f}")
    fit(cfg, train, steps, report=lambda c: f"held-out R^2 {r_squared(c, held_out):.3f}")


def offline(steps: int, batches: int) -> None:
    cfg = scenario(60, 4)
    nvec = team_action_space(cfg).nvec
    rng = np.random.default_rng(0)

    def act(core):
        return rng.integers(0, nvec, size=(core.n,) + nvec.shape)

    data = collect(cfg, act, batches, 123)
    print(f"{len(data[3])} slots; reward std {data[3].std():.1f}")
    critic = fit(cfg, data, steps)

    def values(core, a):
        with torch.no_grad():
            s, o = torch.as_tensor(core.state(), dtype=torch.float32), torch.as_tensor(core.obs, dtype=torch.float32)
            return critic(s, o, torch.as_tensor(a)).numpy()

    compare(cfg, values, act)


if __name__ == "__main__":
    if sys.argv[1] == "checkpoint":
        from_checkpoint(sys.argv[2], int(sys.argv[3]), int(sys.argv[4]))
    elif sys.argv[1] == "onpolicy":
        on_policy(sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5]), int(sys.argv[6]))
    else:
        offline(int(sys.argv[2]), int(sys.argv[3]))
