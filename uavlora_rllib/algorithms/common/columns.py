"""Names of the batch columns and recurrent-state keys that the algorithms share.

One name per concept. RLlib's own columns (obs, actions, rewards, state_in/out, ...) stay
`ray.rllib.core.columns.Columns`; this module holds only what the project adds to a batch.
"""

from __future__ import annotations

from uavlora_rllib.envs.multi_agent import STATE_KEY

# The global state s_t (docs/model.md, "Observations and state"). The env hands it over as
# info[STATE_KEY]; learners that need it (MAPPO's central critic, the QMIX mixer, COMA's
# critic) put it into their train batch under the same name: [B, T(+1), state_dim].
GLOBAL_STATE = STATE_KEY

# Key of the GRU hidden state in Columns.STATE_IN / Columns.STATE_OUT: [B, U, gru_hidden].
HIDDEN = "h"

# QMIX/VDN replay: whether an episode ended by termination (never here: episodes truncate). [B]
TERMINATED = "terminated"

# MAPPO: the value predictions made before the update (normalised space), for value clipping. [B, T, U]
VF_PREDS = "mappo_vf_preds"
