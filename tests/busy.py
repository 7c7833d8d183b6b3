"""Run the test suite on a busy machine: CPU-bound processes beside it (two by default, as many as a
2-core machine has), started before the first test and ended after the last.

    python tests/busy.py [PYTEST ARGS]          # the whole suite, or any selection, with two busy processes
    python -m pytest --busy 2 [PYTEST ARGS]     # the same through the pytest option (tests/conftest.py)

Tests must pass this way: they wait for events and counts, never for wall-clock windows."""
from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
from pathlib import Path

# spins until its parent (the test run) is gone, so an interrupted run leaves nothing behind
SPIN = """
import os
parent = os.getppid()
while os.getppid() == parent:
    for _ in range(1_000_000):
        pass
"""


@contextlib.contextmanager
def busy_processes(count: int):
    """``count`` processes that each keep one core busy, for the duration of the block."""
    procs = [subprocess.Popen([sys.executable, "-c", SPIN], stdin=subprocess.DEVNULL) for _ in range(count)]
    try:
        yield [p.pid for p in procs]
    finally:
        for p in procs:
            with contextlib.suppress(ProcessLookupError):
                os.kill(p.pid, signal.SIGKILL)
            p.wait()


def main(argv: list[str]) -> int:
    tests = Path(__file__).resolve().parent
    return subprocess.call([sys.executable, "-m", "pytest", "--busy", "2", *argv], cwd=tests.parent)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
