"""Can VDN's per_device function class rank an ED's (SF, TP) pairs when the data is good? (issue 23)

br_probe.py found that trained VDN/QMIX leave most EDs off their best response. This separates the function
class from the learning dynamics: log slots of the CI scenario (tests/test_learning.py) played by a BEHAVIOUR
policy with independent per-branch epsilon noise (each ED's (SF, TP) and each UAV's BW replaced by a uniform
one with probability EPS), then fit VDN-S exactly as the learner builds it (BranchingAgentNet, the branch
mean per UAV, the sum over UAVs plus V(s)) by least squares on the slot's reward (gamma 0: the TD target is
the reward), and play the fitted greedy policy on the test's evaluation episodes with br_probe's checks.

With independent noise the best additive fit is each ED's main effect, E[r | its action] over the others'
noise, so near a local optimum its argmax is that optimum: a class that can represent it gives back the
behaviour's choices; one that cannot stays below.

    python docs/history/measurements/offline_fit_probe.py BEHAVIOUR EPS EPISODES UPDATES [CQL]
    BEHAVIOUR: greedy (the per_device reference) | best_fixed | random; $SLOT_HEAD: the agent net's slot_head
    CQL: "bc" fits the behaviour's choices instead (cross-entropy per branch: a control that the network and
         its inputs can express the behaviour's policy), else the weight of a conservative term per slot branch, logsumexp_a Q_k(a) - Q_k(a_taken) (Kumar et al., 2020),
         which pushes the pairs the data rarely tried below the ones it did (default 0)
"""

import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "tests"))

import test_learning as tl  # noqa: E402
from br_probe import probe  # noqa: E402

from uavlora_rllib.algorithms.qmix import branching  # noqa: E402
from uavlora_rllib.algorithms.qmix.qmix_module import VDNMixer  # noqa: E402
from uavlora_rllib.baselines.policies import make_baseline  # noqa: E402
from uavlora_rllib.sim.core import BatchCore  # noqa: E402
from uavlora_rllib.sim.observation import obs_dim  # noqa: E402

CFG = tl.PER_DEVICE
TRAIN_SEED_BASE = 7_000_000  # far from the evaluation episodes' seeds


def collect(behaviour: str, eps: float, episodes: int, rng: np.random.Generator):
    """obs [E, T, U, d], state [E, T, S], actions [E, T, U, L], reward [E, T] under the noisy behaviour."""
    policy = make_baseline(behaviour, CFG, seed=0)
    core = BatchCore(CFG, episodes)
    core.reset([TRAIN_SEED_BASE + i for i in range(episodes)])
    policy.reset(core)
    obs, state, acts, rew = [], [], [], []
    n_pairs = CFG.n_sf * CFG.n_tp
    for _ in range(CFG.episode_len):
        a = np.asarray(policy.act(core))
        obs.append(np.asarray(core.obs, dtype=np.float32).copy())
        state.append(np.asarray(core.state(), dtype=np.float32).copy())
        slot, bw = (x.numpy() for x in branching.branch_indices(torch.as_tensor(a), CFG.n_tp))
        flip = rng.random(slot.shape) < eps
        slot = np.where(flip, rng.integers(0, n_pairs, slot.shape), slot)
        flip = rng.random(bw.shape) < eps
        bw = np.where(flip, rng.integers(0, CFG.n_bw, bw.shape), bw)
        a = branching.env_actions(torch.as_tensor(slot), torch.as_tensor(bw), CFG.n_tp).numpy()
        res = core.step(a)
        acts.append(a)
        rew.append(np.asarray(res.reward, dtype=np.float32))
    stack = lambda xs: torch.as_tensor(np.stack(xs, axis=1))  # noqa: E731
    return stack(obs), stack(state), stack(acts), stack(rew)


def build():
    return branching.BranchingAgentNet(
        obs_dim=obs_dim(CFG), n_agents=CFG.n_uavs,
        quota=CFG.quota, n_pairs=CFG.n_sf * CFG.n_tp, n_bw=CFG.n_bw, n_tp=CFG.n_tp, fc_hidden=128, gru_hidden=128, head_hidden=64,
        share=False, slot_head=os.environ.get("SLOT_HEAD", "per_slot"), dueling=True,
    )  # fmt: skip


class Greedy:
    """The fitted net's greedy per-branch actions, GRU state carried over the episode."""

    name = "fitted"

    def __init__(self, net):
        self.net, self.h = net, None

    def reset(self, core):
        self.h = torch.zeros(core.n, CFG.n_uavs, self.net.gru_hidden)

    def act(self, core):
        with torch.no_grad():
            obs = torch.as_tensor(np.asarray(core.obs, dtype=np.float32)).unsqueeze(1)
            slot_q, bw_q, self.h = self.net(obs, self.h)
            s, b = branching.greedy(slot_q[:, -1], bw_q[:, -1])
            return branching.env_actions(s, b, CFG.n_tp).numpy()


def main():
    behaviour, eps, episodes, updates = sys.argv[1], float(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
    bc = len(sys.argv) > 5 and sys.argv[5] == "bc"
    cql = float(sys.argv[5]) if len(sys.argv) > 5 and not bc else 0.0
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    t0 = time.perf_counter()
    cache = Path(f"/tmp/offline_fit_{behaviour}_{eps}_{episodes}.pt")  # the log is the slow part: reuse it
    if cache.exists():
        obs, state, acts, rew = torch.load(cache)
    else:
        obs, state, acts, rew = collect(behaviour, eps, episodes, rng)
        torch.save((obs, state, acts, rew), cache)
    print(f"{behaviour} eps {eps} cql {cql}: {episodes} episodes logged in {time.perf_counter() - t0:.0f} s, "
          f"mean reward {rew.mean():.3f}", flush=True)  # fmt: skip
    net = build()
    mixer = VDNMixer(state.shape[-1], 32, state_bias=True)
    opt = torch.optim.Adam([*net.parameters(), *mixer.parameters()], lr=1e-3)
    quota = CFG.quota
    for step in range(1, updates + 1):
        idx = torch.as_tensor(rng.integers(0, episodes, 16))
        o, s, a, r = obs[idx], state[idx], acts[idx], rew[idx]
        slot_q, bw_q, _ = net(o, torch.zeros(len(idx), CFG.n_uavs, net.gru_hidden))
        si, bi = branching.branch_indices(a, CFG.n_tp)
        sv, bv = branching.taken(slot_q, bw_q, si, bi)
        q_tot = mixer(branching.aggregate(sv, bv, branching.active_slots(o, quota)), s)
        loss = ((q_tot - r) ** 2).mean()
        if bc:
            active = branching.active_slots(o, quota)
            ce = torch.nn.functional.cross_entropy
            loss = ce(slot_q[active], si[active]) + ce(bw_q.flatten(0, -2), bi.flatten())
        if cql:
            active = branching.active_slots(o, quota)
            gap = torch.logsumexp(slot_q, -1) - sv  # [B, T, U, K]
            loss = loss + cql * gap[active].mean()
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_([*net.parameters(), *mixer.parameters()], 10.0)
        opt.step()
        if step % max(1, updates // 4) == 0:
            mse, var = float(((q_tot - r) ** 2).mean().detach()), float(r.var())
            print(f"  update {step}: mse {mse:.4f} (reward variance {var:.4f})", flush=True)
            probe(Greedy(net), CFG, f"fit@{step}")


if __name__ == "__main__":
    main()
