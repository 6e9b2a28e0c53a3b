"""common/torch_process.py: the per-process settings of a trial's torch processes."""

from __future__ import annotations

import ctypes
import os
import shutil
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


def _clean_env(**extra: str) -> dict[str, str]:
    """This process's environment without the allocator settings a machine may carry."""
    keep = {
        k: v for k, v in os.environ.items() if not k.startswith("MALLOC_") and k not in ("GLIBC_TUNABLES", "LD_PRELOAD")
    }
    return {**keep, **extra}


def _probe(mode: str, env: dict[str, str]) -> list[str]:
    out = subprocess.run([sys.executable, "-c", _PROBE, mode], capture_output=True, text=True, check=True, env=env)
    return out.stdout.split()


def _has_mallinfo2() -> bool:
    return sys.platform.startswith("linux") and hasattr(ctypes.CDLL(None), "mallinfo2")


glibc_233 = pytest.mark.skipif(not _has_mallinfo2(), reason="glibc >= 2.33 (mallinfo2)")


@glibc_233
def test_large_blocks_come_from_the_heap_and_stay_there():
    """By default a 64 MiB block is mmap'd (and unmapped on free); after retain_freed_memory it
    comes from the heap, which keeps it once freed."""
    assert _probe("default", _clean_env()) == ["None", "64", "False"]
    assert _probe("retain", _clean_env()) == ["True", "0", "True"]


@glibc_233
@pytest.mark.parametrize("var, value", [("MALLOC_ARENA_MAX", "2"), ("GLIBC_TUNABLES", "glibc.malloc.trim_threshold=1")])
def test_a_users_own_allocator_settings_are_left_alone(var, value, monkeypatch):
    assert _probe("retain", _clean_env(**{var: value}))[:2] == ["False", "64"]
    monkeypatch.setenv(var, value)
    assert torch_process.retain_freed_memory() is False


@glibc_233
def test_tunables_of_other_glibc_parts_do_not_count():
    assert _probe("retain", _clean_env(GLIBC_TUNABLES="glibc.pthread.rseq=0"))[:2] == ["True", "0"]


@glibc_233
@pytest.mark.skipif(shutil.which("cc") is None, reason="needs a C compiler to build a preloaded malloc")
def test_a_preloaded_allocator_is_left_alone(tmp_path):
    """With another malloc preloaded (as jemalloc or tcmalloc would be), glibc's settings would
    change nothing: retain_freed_memory says so."""
    src = tmp_path / "shim.c"
    src.write_text(
        "#include <stddef.h>\nextern void *__libc_malloc(size_t);\nvoid *malloc(size_t n) { return __libc_malloc(n); }\n"
    )
    lib = tmp_path / "libshim.so"
    subprocess.run(["cc", "-shared", "-fPIC", "-o", str(lib), str(src)], check=True, capture_output=True)
    assert _probe("retain", _clean_env(LD_PRELOAD=str(lib)))[0] == "False"


_FILL_PROBE = """
import torch
from uavlora_rllib.algorithms.common.torch_process import setup_torch_process
torch.use_deterministic_algorithms(True)  # what RLlib's set_torch_seed does
filled = torch.empty(1 << 12).isnan().all().item()  # the fill's effect (content after it is arbitrary)
setup_torch_process(1)
print(filled, torch.utils.deterministic.fill_uninitialized_memory, torch.are_deterministic_algorithms_enabled(),
      torch.get_num_threads())
"""


def test_new_tensors_stay_unfilled_with_deterministic_algorithms_on():
    """RLlib's deterministic mode NaN-fills every torch.empty; a trial's process turns only the fill off."""
    out = subprocess.run(
        [sys.executable, "-c", _FILL_PROBE], capture_output=True, text=True, check=True, env=_clean_env()
    )
    assert out.stdout.split() == ["True", "False", "True", "1"]
