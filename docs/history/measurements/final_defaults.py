"""Select the rows of learning.jsonl that ran the current registry defaults, for the seed-mean table.

    python docs/history/measurements/final_defaults.py > /tmp/final.jsonl
    python docs/history/measurements/learning_table.py /tmp/final.jsonl

Tags name the defaults of their time, and a later session's tag does not re-run learners whose
defaults it did not change. Which tags hold today's defaults, per learner:
  - mappo, ippo: `defaults-s3b` (GAE lambda 0, entropy 0.001, one actor per UAV), and MAPPO's
                 `lambda_=0` rows (that override on defaults-s3: the same setting) and `defaults-s6`
                 rows (session 6 changed no default; it ran the 60x8 seeds still missing);
  - qmix:        `defaults-s5` (updates_per_episode 0.25) and the candidate rows `updates_per_iteration=4`
                 (4 updates per iteration of 16 episodes: the same ratio with bench_learn's 16 envs
                 per runner);
  - vdn:         `defaults-s4` and `defaults-s5` (state_bias on, one update per episode) and the
                 candidate row `vdn_state_bias=true` (the same setting under the switch's first name);
                 its `updates_per_iteration=4` rows are the ratio QMIX took and VDN did not;
  - coma:        `defaults-s3` and `defaults-s3b` (s3 -> s3b changed only MAPPO/IPPO), the
                 `defaults (updates_per_iteration=8)` row at 60x8 (run after that default was set), and
                 `defaults-s6` (the 60x8 seeds 1-2).
Superseded: QMIX's `defaults-s3`/`defaults-s3b` rows ran one update per episode, its default before
session 5.
One row per (V, U, action mode, learner, budget, seed): the last one in the file. Every selected row
is re-tagged "final defaults" so that the table groups the seeds of one learner and scenario.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

FINAL_TAGS = {
    "mappo": {"defaults-s3b", "lambda_=0", "defaults-s6"},
    "ippo": {"defaults-s3b"},
    "qmix": {"defaults-s5", "updates_per_iteration=4"},
    "coma": {"defaults-s3", "defaults-s3b", "defaults (updates_per_iteration=8)", "defaults-s6"},
    "vdn": {"defaults-s4", "defaults-s5", "vdn_state_bias=true"},
}


def main(path: str = str(Path(__file__).with_name("learning.jsonl"))) -> None:
    chosen: dict[tuple, dict] = {}
    for line in Path(path).read_text().splitlines():
        if not line.strip():
            continue
        row = json.loads(line)
        if row.get("tag") not in FINAL_TAGS.get(row["learner"], ()):
            continue
        key = (row["n_eds"], row["n_uavs"], row["action_mode"], row["learner"], row["budget_env_steps"], row["seed"])
        chosen[key] = {**row, "tag": "final defaults", "source_tag": row["tag"]}
    for row in chosen.values():
        sys.stdout.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main(*sys.argv[1:])
