"""Process memory settings for CPU training and stepping the environment: keep freed memory in the process.

A SMART training step on the CPU allocates and frees gigabytes of short-lived tensors (relative
positional embeddings of every neighbour pair, and their gradients). glibc's allocator serves
every block above 32 MB with a fresh ``mmap`` and returns it with ``munmap`` when it is freed, so
each step pays for zero-filling every page again in the kernel: measured on the project's 2-core
machine, 0.6-0.7 million page faults and about half of the step's time in the kernel.

:func:`keep_freed_memory` tells glibc (``mallopt``) to serve large blocks from its heap and not to
give freed memory back to the system, so later steps reuse pages that are already mapped. The
process keeps its peak size for its lifetime (what a training process does anyway). It changes
where memory comes from, never a number the model computes. Elsewhere than glibc it does nothing.

``smart-marl train`` applies it, and so does every environment on the CPU (``envs._core.TrafficCore``): a
step allocates and frees tensors of megabytes too; with these settings an environment benchmark process
took a third to a fifth of the page faults and 0.8 s of system time instead of 2-3 s
(``docs/benchmarks/env_keep_freed_memory_ab_2026-11-26.jsonl``).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

# glibc <malloc.h>
_M_TRIM_THRESHOLD = -1
_M_TOP_PAD = -2
_M_MMAP_MAX = -4

_applied: bool | None = None


def keep_freed_memory() -> bool:
    """Serve large allocations from the heap and keep freed memory for reuse (glibc only).

    Returns whether the settings are in force. Idempotent; safe to call from any process (DataLoader
    workers forked later inherit the settings).
    """
    global _applied
    if _applied is not None:
        return _applied
    _applied = False
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    ok = mallopt(_M_MMAP_MAX, 0)  # no mmap'd blocks: everything from the heap (mmap stays the fallback)
    ok &= mallopt(_M_TRIM_THRESHOLD, 2**31 - 1)  # never trim the heap's top back to the system
    ok &= mallopt(_M_TOP_PAD, 64 << 20)  # grow the heap in 64 MB steps
    _applied = bool(ok)
    return _applied
