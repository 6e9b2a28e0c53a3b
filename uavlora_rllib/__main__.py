"""`python -m uavlora_rllib ARGS`: the same as the `uavlora` console command (uavlora_rllib.cli)."""

import sys

from uavlora_rllib.cli import main

sys.exit(main())
