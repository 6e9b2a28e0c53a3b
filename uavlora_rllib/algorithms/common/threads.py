"""torch's intra-op thread count of a process: the trial's `Resources.torch_threads`.

Every process that runs torch for a trial sets it: the trial's own process (tune's trainable,
the bench CLIs) and, through their RLModule's setup, remote env runners and learners. torch's
own default (one thread per core) oversubscribes the CPUs that several such processes share.
"""

from __future__ import annotations


def set_torch_threads(threads: int | None) -> None:
    """Use `threads` intra-op threads in this process; None or 0: leave torch's setting."""
    if threads:
        import torch

        torch.set_num_threads(int(threads))
