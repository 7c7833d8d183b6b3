"""Compiling an estimator's kernels before a session uses it, never on the event loop.

Estimators with numba kernels (``jit_kernels``) compile them on first use, which takes seconds to
tens of seconds and would freeze every session if it happened on the service's event loop.
``warm_off_loop`` first compiles them in a separate process (``python -m service.estimators.warm
NAME [PARAMS_JSON]``), which fills the on-disk cache without competing with the service for its
interpreter lock, then runs a few samples in a worker thread, which loads the cached code into this
process. The container image runs the same command at build time.

The hand pipeline's own kernels (the optical fit, the OpenXR joint poses, the gesture values and the recogniser's step, the flexion-axis fit, a frame's text) are warmed the same way, under the name
``pipeline``, with whatever estimator comes first. When every kernel to warm is already in the on-disk
cache (the usual case after the first run, and in the container image) the separate process is skipped:
loading cached code takes a fraction of a second, where starting that process costs a full interpreter
start-up. Without an on-disk cache (no writable folder: ``service.JIT_CACHE`` false) it is skipped too: its compile
would be lost, and this process compiles the kernels anyway.

Beside live sessions two things must not take their time. The separate process runs at the idle
scheduling priority (``--background --idle``: Linux's ``SCHED_IDLE``): it gets a core only while no other
process wants it, and gives it up at once to one that wakes. At any niceness a process that wakes (a hand
worker with a batch, the web process with a frame) waits for the compile's time slice to end, up to a
scheduler tick: measured on this 2-core machine, a process at niceness 5 that sleeps 2 ms and works 0.3 ms,
two at once, woke p99 0.6-0.9 ms late on an idle machine, 3.9-4.1 ms beside two busy processes at niceness
10 or 19 (max 7-12 ms), 0.49 ms beside two at ``SCHED_IDLE`` (max 7.6-8.3); a frame passes such a wake three
times (web process, worker, web process). A process at the idle priority gets almost no CPU on a machine
whose cores other work keeps busy (at niceness 19 a switch to an estimator not in the cache did not complete
within 300 s), so a compile not done after ``COMPILE_IDLE_S`` is stopped and started again at niceness
``COMPILE_NICE`` (``Compile``): numba keeps each kernel in the on-disk cache as it is compiled, so the
second process goes on from where the first stopped. The samples that load the
cached code into a serving process run in a thread with the interpreter's lock handed over every
``LOAD_SWITCH_INTERVAL_S`` (``sharing_the_interpreter``; loading ``inertial`` held it for 130 ms, the
default interval lets a thread keep it 5 ms at a time)."""
from __future__ import annotations

import asyncio
import contextlib
import json
import os
import subprocess
import sys
import threading
import time

import numpy as np

_WARM: set[str] = set()


PIPELINE = "pipeline"
"""The name under which the hand pipeline's own kernels are warmed."""

COMPILE_NICE = 5
"""niceness of the separate process that compiles kernels (``--background`` without ``--idle``, and ``Compile``'s
second process): the hand workers' default"""
COMPILE_IDLE_S = 30.0
"""how long ``Compile``'s process runs at the idle priority before it is started again at ``COMPILE_NICE``, s
(compiling ``inertial`` and the pipeline's kernels takes 10-12 s of a core on this machine)"""
LOAD_SWITCH_INTERVAL_S = 0.0005
"""the interpreter's switch interval while kernels load in a thread of a serving process, s (default 0.005)"""
_sharing = [0, None]                         # threads loading now, the switch interval before the first
_sharing_lock = threading.Lock()


@contextlib.contextmanager
def sharing_the_interpreter():
    """While the block runs (kernels loading in a thread beside threads that serve sessions), the
    interpreter's lock changes hands every ``LOAD_SWITCH_INTERVAL_S``: a serving thread that wants it
    waits that long at most, not the default 5 ms, each time it gets it back (a frame's path takes it
    several times). The interval before is restored when the last such block ends."""
    with _sharing_lock:
        if _sharing[0] == 0:
            _sharing[1] = sys.getswitchinterval()
            sys.setswitchinterval(LOAD_SWITCH_INTERVAL_S)
        _sharing[0] += 1
    try:
        yield
    finally:
        with _sharing_lock:
            _sharing[0] -= 1
            if _sharing[0] == 0:
                sys.setswitchinterval(_sharing[1])


def compile_command(name: str, params: dict | None = None, idle: bool = False) -> list[str]:
    """The separate process that compiles the kernels of ``name`` (and the pipeline's) into the on-disk
    cache, at a lower priority (``COMPILE_NICE``; with ``idle``, the idle scheduling priority)."""
    return [sys.executable, "-m", "service.estimators.warm", "--background", *(["--idle"] if idle else []), name,
            json.dumps(params or {})]


def lower_priority(idle: bool) -> None:
    """This process's priority for compiling beside a serving one: with ``idle`` the idle scheduling
    priority (``SCHED_IDLE``, where the system has it), else (or where it has not) niceness ``COMPILE_NICE``
    (at least: a process already nicer stays so)."""
    if idle and hasattr(os, "SCHED_IDLE"):
        try:
            os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
            return
        except OSError:
            pass
    with contextlib.suppress(OSError):
        os.nice(COMPILE_NICE - os.nice(0))


class Compile:
    """The separate process compiling the kernels of ``name`` (``compile_command``), first at the idle
    priority and, if it has not finished after ``COMPILE_IDLE_S``, stopped and started again at
    ``COMPILE_NICE`` (module docstring; what the first compiled is in the cache). ``poll`` as
    ``subprocess.Popen``'s (for a caller that looks now and then), ``wait`` for one that blocks. Raises
    ``OSError`` when no process can be started."""

    def __init__(self, name: str, params: dict | None = None):
        self.name, self.params = name, params
        self.idle = hasattr(os, "SCHED_IDLE")
        self.started = time.monotonic()
        self.process = self._start()

    def _start(self) -> subprocess.Popen:
        return subprocess.Popen(compile_command(self.name, self.params, idle=self.idle), stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL)

    def _at_nice(self) -> None:
        self.process.kill()
        self.process.wait()
        self.idle = False
        self.process = self._start()

    def poll(self) -> int | None:
        code = self.process.poll()
        if code is None and self.idle and time.monotonic() - self.started >= COMPILE_IDLE_S:
            self._at_nice()
        return code

    def wait(self) -> int:
        if self.idle:
            try:
                return self.process.wait(max(0.0, self.started + COMPILE_IDLE_S - time.monotonic()))
            except subprocess.TimeoutExpired:
                self._at_nice()
        return self.process.wait()


def _pipeline_kernels() -> tuple:
    from gestures import values
    from ..model import openxr_frame_kernel, openxr_kernel
    from ..pipeline import frame_text_kernel, mounting_kernel, optical_kernel
    return (openxr_kernel.joint_poses, optical_kernel.at_in, optical_kernel.usable_in, optical_kernel.keeps,
            optical_kernel.pose_keeps_in, optical_kernel.add, values.values_kernel, mounting_kernel.correct,
            mounting_kernel.fit, frame_text_kernel.merge, values.step_kernel, openxr_frame_kernel.frame_poses)


def _kernels(name: str) -> tuple:
    """The numba dispatchers behind ``name`` (an estimator or ``PIPELINE``); empty for none."""
    if name == PIPELINE:
        return _pipeline_kernels()
    from .registry import REGISTRY
    cls = REGISTRY.get(name)
    return tuple(getattr(cls, "kernels", ())) if cls is not None and cls.jit_kernels else ()


def _on_disk(kernels: tuple) -> bool:
    """Whether every dispatcher has compiled code for this source in the on-disk cache (numba's index
    for it exists and matches the source); False when that cannot be told."""
    try:
        return bool(kernels) and all(k._cache._cache_file._load_index() for k in kernels)
    except Exception:                      # numba internals differ: assume not cached
        return False


def _warm_pipeline() -> None:
    from ..model.hand import default_calibration
    from ..model.openxr import joint_poses_compiled

    from ..pipeline import frame_text_kernel, optical_kernel
    from ..pipeline.mounting import HandMountings
    from ..pipeline.optical import OpticalTrack

    from gestures.values import frame_values

    calib = default_calibration("right")
    angles = {n: np.zeros(g.n_phalanges) for n, g in calib.fingers.items()}
    frame_values(angles, joint_poses_compiled(calib, angles, np.eye(3), np.zeros(3)), 1.0, 1.0)
    track = OpticalTrack()
    for k in range(3):
        track.add(0.01 * k, np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]), True)     # (``optical_kernel.add``)
    track.at(0.015)
    optical_kernel.usable_in(np.array([0.005, 0.015]), *track.kernel_args(), np.empty((2, 24)),
                             np.empty(2, dtype=np.int64), track.run_scratch())
    track.add_keeps(0.03, 0.015)
    optical_kernel.pose_keeps_in(0.03, 0.015, np.array([0.015]), *track.kernel_args(), track._max_poses,
                                 np.empty((1, 24)), np.empty(1, dtype=np.int64), track.run_scratch())   # (``HandSession._pose_keeps``)
    mountings = HandMountings(calib)
    rows = mountings.rows(tuple(calib.sensor_ids))
    raw = np.zeros((len(rows), 2, 3))
    mountings.correct(rows, raw)
    mountings.fit(rows, raw, np.concatenate([np.eye(3).ravel(), np.zeros(9)]),
                  np.zeros(sum(angles[n].shape[0] for n in angles)), np.ones(len(calib.fingers), dtype=np.bool_))
    # the gesture recogniser's step on a pipeline frame (``GestureRecognizer._step``), first and later frames
    from gestures.recognizer import GestureRecognizer
    from ..model.openxr import FingerAngles, angles_layout, joint_pose_arrays
    from ..pipeline.hand import HandFrame, JointPoses
    flat = FingerAngles(np.zeros(sum(angles[n].shape[0] for n in angles)),
                        angles_layout(tuple(angles), tuple(angles[n].shape[0] for n in angles)))
    recognizer = GestureRecognizer()
    for k in range(2):
        recognizer.update(HandFrame(0.01 * k, k, "right", flat, {}, np.eye(3), np.zeros(3),
                                    JointPoses(*joint_pose_arrays(calib, flat, np.eye(3), np.zeros(3))), {}))
    # a frame's joint poses into its numbers (``HandSession._frame``: the angles a view of them)
    from ..model.openxr import JOINT_NAMES, _packed_calibration
    from ..model.openxr_frame_kernel import frame_poses
    numbers = np.zeros(flat.layout.n + 7 * len(JOINT_NAMES))
    frame_poses(_packed_calibration(calib), numbers[:flat.layout.n], flat.layout.padded, np.eye(3), np.zeros(3), numbers)
    # a frame's text (``frame_text``: the numbers and small parts as bytes, the fixed parts read-only)
    frame_text_kernel.merge(b"[1.0]", b"{}{}{}", 2, 2,
                            np.frombuffer(b",,,,,", np.uint8), np.arange(1, 6, dtype=np.int64),
                            np.array([0, 1, 1], dtype=np.int64), np.empty(32, dtype=np.uint8))


def _to_warm(name: str) -> list[str]:
    """What warming ``name`` has to do in this process: the pipeline's kernels once, then the
    estimator's if it has kernels."""
    names = [PIPELINE] if PIPELINE not in _WARM else []
    from .registry import REGISTRY
    cls = REGISTRY.get(name)
    if cls is not None and cls.jit_kernels and name not in _WARM:
        names.append(name)
    return names


def _compile_apart(names: list[str]) -> bool:
    """Whether the separate process should compile the kernels of ``names`` first: some are not in the
    on-disk cache, and there is one (``JIT_CACHE``). Without a cache (no writable folder) its compile would
    be lost and this process would compile them all again: a read-only service's start and a switch took
    twice the CPU."""
    from .. import JIT_CACHE
    return JIT_CACHE and not _on_disk(tuple(k for n in names for k in _kernels(n)))


def needs_compiling(name: str) -> bool:
    """Whether warming ``name`` in this process needs the separate process first: some of its kernels
    (or the pipeline's, not yet warm here) are not in the on-disk cache (``_compile_apart``)."""
    names = _to_warm(name)
    return bool(names) and _compile_apart(names)


def warm(name: str, params: dict | None = None) -> None:
    """Run a few samples through the estimator ``name`` so that its kernels are compiled (or loaded
    from the cache) in this process (``PIPELINE``: the hand pipeline's kernels). Raises ``ValueError``
    for an unknown name or bad settings."""
    from .registry import estimator_class

    with sharing_the_interpreter():
        if name == PIPELINE:
            _warm_pipeline()
            return
        _warm_estimator(estimator_class(name), params)
    _WARM.add(name)


def _warm_estimator(cls, params: dict | None) -> None:
    from ..model.hand import default_calibration
    from ..model.kinematics import BaseMotion

    settings = cls.Settings(**(params or {}))
    geom = default_calibration("right").finger("index")
    estimator = cls(geom, settings=settings)
    n = len(geom.sensors)
    z = np.zeros(3)
    hand = BaseMotion(np.eye(3), z, z, z, z, z)
    gyr, acc = np.zeros((n, 3)), np.tile([0.0, 9.81, 0.0], (n, 1))
    for k in range(3):
        estimator.update(0.005 * k, gyr, acc, hand)
    from .chain import ChainHand
    if ChainHand.takes(estimator, 0.015):           # the hand pipeline's one call for all its fingers
        together = ChainHand()
        together.advance(0.015, [estimator], gyr, acc, hand)
        _warm_steady_tick(together, estimator, hand)


def _warm_steady_tick(together, estimator, hand) -> None:
    """The pipeline's steady tick (``pipeline.tick_kernel``: the flexion-axis fits and ``run_hand`` in one
    call) on ``together``'s one finger, with the argument types the pipeline passes."""
    from ..model.hand import default_calibration
    from ..pipeline.mounting import HandMountings
    from ..pipeline.tick_kernel import steady_tick

    calib = default_calibration("right")
    fits = HandMountings(calib)
    rows = fits.rows(tuple(s.id for s in estimator.geom.sensors))
    raw = np.zeros((len(rows), 2, 3))
    raw[:, 1, 1] = 9.81
    gather = np.arange(len(rows), dtype=np.int64)
    phi = np.zeros(sum(g.n_phalanges for g in calib.fingers.values()))
    started = np.ones(len(calib.fingers), dtype=np.bool_)
    together.cross_offsets = np.zeros((len(rows), 3))
    together.advance_in(steady_tick, (fits.state, fits._meta, rows, fits._st, raw, np.empty_like(raw), phi, started,
                                      rows, 2 * gather, 2 * gather + 1), 0.02, [estimator], hand, len(rows))
    _warm_steady_run(together, estimator, fits, rows, raw, phi, started, gather)


def _warm_steady_run(together, estimator, fits, rows, raw, phi, started, gather) -> None:
    """The pipeline's run of steady ticks (``pipeline.tick_kernel.steady_run_in``, its work arrays kept) with the
    argument types the pipeline passes (``HandSession._steady_run``), on a track without poses: compiled (or
    loaded), nothing done (no tick is steady without the optics)."""
    from ..pipeline.optical import OpticalTrack
    from ..pipeline.tick_kernel import steady_run_in

    ts = [0.025]
    track = OpticalTrack()
    together.advance_run(steady_run_in, (np.array(ts), *track.kernel_args(), -np.inf, 0.15, False,
                                      np.empty((1, 24)), np.empty((1, 18)), np.empty(1), 0, np.zeros(0, dtype=np.int64),
                                      fits.state, fits._meta, rows,
                                      fits._st, raw[None], np.empty_like(raw[None]), np.tile(phi, (2, 1)), started,
                                      rows, 2 * gather, 2 * gather + 1), ts, [estimator], len(rows),
                         track.run_scratch())


def cached_not_warm() -> list[str]:
    """The estimators with kernels whose compiled code is in the on-disk cache but not yet loaded in this
    process: what a hand worker loads ahead, in the background, once it serves
    (``ServiceSettings.preload_kernels``), so that a session switched to one later does not wait for the
    load (0.32 s of CPU for ``inertial``)."""
    from .registry import REGISTRY

    return [n for n, c in REGISTRY.items() if c.jit_kernels and n not in _WARM and _on_disk(_kernels(n))]


def is_warm(name: str) -> bool:
    """Whether a hand of this process can switch to estimator ``name`` without compiling: it has no
    kernels, or ``warm`` ran for it here (unknown names: True, their validation answers)."""
    from .registry import REGISTRY

    cls = REGISTRY.get(name)
    return cls is None or not cls.jit_kernels or name in _WARM


async def warm_off_loop(name: str, params: dict | None = None) -> None:
    """``warm`` without blocking the event loop (module docstring); a no-op for estimators without
    kernels and for those already warm in this process. Bad names or settings are left for the
    caller's own validation to report."""
    names = _to_warm(name)
    if not names:
        return
    if _compile_apart(names):
        try:
            compiling = Compile(names[-1], params)
        except OSError:
            pass                            # no separate process here: the thread compiles instead
        else:
            await asyncio.to_thread(compiling.wait)
    for n in names:
        try:
            await asyncio.to_thread(warm, n, params if n == name else None)
        except ValueError:
            return
        _WARM.add(n)


def warm_ahead(name: str, params: dict | None = None) -> None:
    """``warm_off_loop`` for a caller already off the event loop (a thread of the API's pool): the
    separate process, then the samples here. A no-op where ``warm_off_loop`` is one."""
    names = _to_warm(name)
    if not names:
        return
    if _compile_apart(names):
        try:
            Compile(names[-1], params).wait()
        except OSError:
            pass
    for n in names:
        try:
            warm(n, params if n == name else None)
        except ValueError:
            return
        _WARM.add(n)


def main(argv: list[str]) -> int:
    if argv[:1] == ["--background"]:               # beside a serving process: a lower priority
        idle = argv[1:2] == ["--idle"]
        argv = argv[1 + idle:]
        lower_priority(idle)
    if not argv:
        print("usage: python -m service.estimators.warm [--background [--idle]] NAME [PARAMS_JSON] (NAME: all for "
              "every estimator; the pipeline's kernels are always warmed; --background: at a lower priority, "
              "--idle: the idle scheduling priority)")
        return 2
    from .registry import REGISTRY
    names = [PIPELINE] + ([n for n, c in REGISTRY.items() if c.jit_kernels] if argv[0] == "all" else [argv[0]])
    params = json.loads(argv[1]) if len(argv) > 1 else {}
    for name in dict.fromkeys(names):
        warm(name, None if name == PIPELINE else params)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
