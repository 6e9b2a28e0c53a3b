"""common/torch_process.py: the per-process settings of a trial's torch processes."""

from __future__ import annotations

import subprocess
import sys

import pytest

from uavlora_rllib.algorithms.common import torch_process

# mallinfo2 (glibc >= 2.33): hblkhd = bytes in mmap'd blocks, arena = bytes of the heap
_PROBE = """
import ctypes, sys
from uavlora_rllib.algorithms.common.torch_process import retain_freed_memory
class Info(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in
                "arena ordblks smblks hblks hblkhd usmblks fsmblks uordblks fordblks keepcost".split()]
libc = ctypes.CDLL(None)
libc.mallinfo2.restype = Info
took = retain_freed_memory() if sys.argv[1] == "retain" else None
block = bytearray(64 << 20)  # 64 MiB through malloc
info = libc.mallinfo2()
del block
after = libc.mallinfo2()
print(took, info.hblkhd >> 20, after.arena >= 64 << 20)
"""


def _probe(mode: str, env: dict[str, str] | None = None) -> list[str]:
    out = subprocess.run([sys.executable, "-c", _PROBE, mode], capture_output=True, text=True, check=True, env=env)
    return out.stdout.split()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's allocator")
def test_large_blocks_come_from_the_heap_and_stay_there():
    """By default a 64 MiB block is mmap'd (and unmapped on free); after retain_freed_memory it
    comes from the heap, which keeps it once freed."""
    assert _probe("default") == ["None", "64", "False"]
    assert _probe("retain") == ["True", "0", "True"]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's allocator")
@pytest.mark.parametrize("var", ["MALLOC_ARENA_MAX", "GLIBC_TUNABLES"])
def test_a_users_own_allocator_settings_are_left_alone(var, monkeypatch):
    import os

    env = {**os.environ, var: "2" if var.startswith("MALLOC") else "glibc.malloc.trim_threshold=1"}
    assert _probe("retain", env)[:2] == ["False", "64"]
    monkeypatch.setenv(var, env[var])
    assert torch_process.retain_freed_memory() is False
