"""Compiling an estimator's kernels before a session uses it, never on the event loop.

Estimators with numba kernels (``jit_kernels``) compile them on first use, which takes seconds to
tens of seconds and would freeze every session if it happened on the service's event loop.
``warm_off_loop`` first compiles them in a separate process (``python -m service.estimators.warm
NAME [PARAMS_JSON]``), which fills the on-disk cache without competing with the service for its
interpreter lock, then runs a few samples in a worker thread, which loads the cached code into this
process. The container image runs the same command at build time."""
from __future__ import annotations

import asyncio
import json
import sys

import numpy as np

_WARM: set[str] = set()


def warm(name: str, params: dict | None = None) -> None:
    """Run a few samples through the estimator ``name`` so that its kernels are compiled (or loaded
    from the cache) in this process. Raises ``ValueError`` for an unknown name or bad settings."""
    from ..model.hand import default_calibration
    from ..model.kinematics import BaseMotion
    from .registry import estimator_class

    cls = estimator_class(name)
    settings = cls.Settings(**(params or {}))
    geom = default_calibration("right").finger("index")
    estimator = cls(geom, settings=settings)
    n = len(geom.sensors)
    z = np.zeros(3)
    hand = BaseMotion(np.eye(3), z, z, z, z, z)
    gyr, acc = np.zeros((n, 3)), np.tile([0.0, 9.81, 0.0], (n, 1))
    for k in range(3):
        estimator.update(0.005 * k, gyr, acc, hand)


async def warm_off_loop(name: str, params: dict | None = None) -> None:
    """``warm`` without blocking the event loop (module docstring); a no-op for estimators without
    kernels and for those already warm in this process. Bad names or settings are left for the
    caller's own validation to report."""
    from .registry import REGISTRY

    cls = REGISTRY.get(name)
    if cls is None or not cls.jit_kernels or name in _WARM:
        return
    try:
        proc = await asyncio.create_subprocess_exec(sys.executable, "-m", "service.estimators.warm", name,
                                                    json.dumps(params or {}), stdout=asyncio.subprocess.DEVNULL,
                                                    stderr=asyncio.subprocess.DEVNULL)
        await proc.wait()
    except OSError:
        pass                                # no separate process here: the thread compiles instead
    try:
        await asyncio.to_thread(warm, name, params)
    except ValueError:
        return
    _WARM.add(name)


def warm_ahead(name: str, params: dict | None = None) -> None:
    """``warm_off_loop`` for a caller already off the event loop (a thread of the API's pool): the
    separate process, then the samples here. A no-op where ``warm_off_loop`` is one."""
    import subprocess

    from .registry import REGISTRY

    cls = REGISTRY.get(name)
    if cls is None or not cls.jit_kernels or name in _WARM:
        return
    try:
        subprocess.run([sys.executable, "-m", "service.estimators.warm", name, json.dumps(params or {})],
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=False)
    except OSError:
        pass
    try:
        warm(name, params)
    except ValueError:
        return
    _WARM.add(name)


def main(argv: list[str]) -> int:
    if not argv:
        print("usage: python -m service.estimators.warm NAME [PARAMS_JSON] (NAME: all for every estimator)")
        return 2
    from .registry import REGISTRY
    names = [n for n, c in REGISTRY.items() if c.jit_kernels] if argv[0] == "all" else [argv[0]]
    params = json.loads(argv[1]) if len(argv) > 1 else {}
    for name in names:
        warm(name, params)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
