"""Where a stuck service is: ``SIGUSR1`` to the web process of ``fingertrack serve`` or to one of its
hand workers writes the stack of every thread of that process to its standard error (the service
log) and the process goes on. The stacks are written by the interpreter's C-level signal handler
(``faulthandler``), so they come also from a process whose event loop is stuck in a long loop or a
long call; a process that does not run at all (stopped, or starved of memory) writes them when it
runs again. ``kill -USR1 PID``; ``fingertrack bench robustness`` does so before it kills a service
that stopped answering."""
from __future__ import annotations

import faulthandler
import signal
import sys

STACKS_SIGNAL = getattr(signal, "SIGUSR1", None)
"""The signal that asks for the stacks (``None`` where there is none, e.g. Windows)."""


def stacks_on_signal() -> bool:
    """From now on, ``STACKS_SIGNAL`` writes every thread's stack to standard error; False where the
    platform has no such signal."""
    if STACKS_SIGNAL is None or not hasattr(faulthandler, "register"):
        return False
    faulthandler.register(STACKS_SIGNAL, file=sys.stderr, all_threads=True)
    return True
