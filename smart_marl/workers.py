"""Worker processes that die with the process that started them.

Used by the stages that fan out over processes (``smart-marl preprocess --workers N``,
``smart-marl generate-sumo --workers N``). A :class:`concurrent.futures.ProcessPoolExecutor`'s
workers wait on a queue whose pipe they also hold open, so when their parent is killed (SIGKILL,
the OOM killer) they never see it close and wait forever, orphaned. :func:`worker_pool`'s workers
ask the kernel for a SIGKILL when their parent goes (Linux ``PR_SET_PDEATHSIG``) and also watch
their parent id from a thread (every other platform, and the window before the first), so none
outlives its parent by more than :data:`PARENT_POLL_S`.
"""

from __future__ import annotations

import ctypes
import multiprocessing
import os
import signal
import sys
import threading
import time
from concurrent.futures import ProcessPoolExecutor

PARENT_POLL_S = 0.5
"""How often a worker checks that the process that started it is still there."""

_PR_SET_PDEATHSIG = 1


def worker_pool(workers: int, spawn: bool = False) -> ProcessPoolExecutor:
    """A process pool of ``workers`` processes that exit when this process exits, however it ends.
    ``spawn``: start them fresh instead of forking (work that runs torch operators: a child forked
    from a process whose torch thread pool has started can hang in its first parallel operator)."""
    context = multiprocessing.get_context("spawn") if spawn else None
    return ProcessPoolExecutor(max_workers=workers, mp_context=context, initializer=die_with_parent, initargs=(os.getpid(),))


def die_with_parent(parent_pid: int) -> None:
    """Make the calling process exit when ``parent_pid`` (its parent) is gone (a pool initializer)."""
    if sys.platform.startswith("linux"):
        try:
            ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
        except (OSError, AttributeError):  # no libc symbol: the watcher below still works
            pass
    if os.getppid() != parent_pid:  # the parent went before the request took effect
        os._exit(1)
    threading.Thread(target=_watch_parent, args=(parent_pid,), name="watch-parent", daemon=True).start()


def _watch_parent(parent_pid: int) -> None:
    while os.getppid() == parent_pid:
        time.sleep(PARENT_POLL_S)
    os._exit(1)


__all__ = ["PARENT_POLL_S", "die_with_parent", "worker_pool"]
