"""Per-process settings of every process that runs torch for a trial: the trial's own process
(tune's trainable, the bench CLIs) and, through their RLModule's setup, remote env runners and
learners (and any other process that builds one of the package's RLModules: evaluation, the
analysis tools that load a checkpoint).

* torch's intra-op thread count, the trial's `Resources.torch_threads`: torch's own default (one
  thread per core) oversubscribes the CPUs that several such processes share.
* glibc's allocator keeps freed memory for reuse. By default it hands every block above 128 kB to
  the kernel (mmap) and back on free, so each fresh activation or gradient tensor of an update
  (30 MB for a per-ED head at V=60/U=8) is zeroed page by page on first touch, which cost as much
  as the arithmetic on it. Keeping them is what jemalloc or tcmalloc would do (PyTorch's CPU
  tuning advice); the process then holds its peak memory (docs/cluster.md#memory). Left to the
  user where they set MALLOC_* or glibc.malloc tunables themselves, or preload another allocator,
  and off other C libraries.
* torch does not fill new memory. RLlib's seeding (`set_torch_seed`) turns on
  `torch.use_deterministic_algorithms`, which by default also fills all memory torch allocates
  uninitialised (`torch.empty`, the outputs of ops) with NaN (integers with their maximum), so that
  a program that reads such memory stays deterministic. Nothing here does
  (tests/test_gru_sequence.py checks the GRU's buffers with the fill on), and torch's documentation
  advises turning the fill off for such programs: it writes every buffer an update allocates
  (the GRU's per-sequence ones included) once more before use. Deterministic algorithms stay on.
"""

from __future__ import annotations

import ctypes
import os
import sys

# glibc's mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD = -1  # bytes free at the heap's top before it is given back
_M_MMAP_MAX = -4  # blocks served by mmap at once (0: none, all from the reusable heap)
_TRIM_NEVER = 2**31 - 1  # mallopt takes an int


def setup_torch_process(threads: int | None) -> None:
    """Use `threads` intra-op threads in this process (None or 0: leave torch's setting), keep
    freed memory for reuse (`retain_freed_memory`) and leave new tensors unfilled (module docstring)."""
    import torch.utils.deterministic

    retain_freed_memory()
    torch.utils.deterministic.fill_uninitialized_memory = False  # type: ignore[attr-defined]  # a module property
    if threads:
        torch.set_num_threads(int(threads))


def retain_freed_memory() -> bool:
    """Tell glibc's malloc to serve large blocks from its heap and never trim it (see the module
    docstring). True where it took effect; idempotent."""
    if not sys.platform.startswith("linux") or "glibc.malloc." in os.environ.get("GLIBC_TUNABLES", ""):
        return False
    if any(k.startswith("MALLOC_") for k in os.environ):
        return False
    process = ctypes.CDLL(None)  # the symbols this process resolves
    if not hasattr(process, "gnu_get_libc_version"):  # another C library (musl, ...)
        return False
    libc = ctypes.CDLL("libc.so.6")
    if ctypes.cast(process.malloc, ctypes.c_void_p).value != ctypes.cast(libc.malloc, ctypes.c_void_p).value:
        return False  # malloc is another allocator's (jemalloc, tcmalloc via LD_PRELOAD)
    mallopt = libc.mallopt
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(mallopt(_M_MMAP_MAX, 0)) and bool(mallopt(_M_TRIM_THRESHOLD, _TRIM_NEVER))
