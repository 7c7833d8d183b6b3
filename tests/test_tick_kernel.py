"""The hand pipeline's steady tick in one compiled call (``pipeline/tick_kernel.py``) against the same
calls made one by one (the pipeline's general path, taken when ``_advanced_together_again`` says no):
the same frames, the same fits and filter states. A recording with its faults (dropped samples, a
silent sensor, an occlusion: the general path between steady stretches) is
``tests/test_pipeline.py``'s steady-tick test; here random readings, a clipped gyro among them."""
from __future__ import annotations

import json

import numpy as np
import pytest

from service.model.units import DEG
from service.pipeline.hand import HandSession
from service.pipeline.tracked import TrackedHand
from service.protocol import parse_message
from service.sim.session import SimConfig, simulate

GYRO_RANGE_RAD_S = 2000.0 * DEG


def _random_readings(seed: int, t0: float, t1: float):
    """The messages of a short realistic recording whose IMU readings between ``t0`` and ``t1`` are
    random (rates up to 6 rad/s, accelerations up to 2 g), with one gyro axis at full scale now and then."""
    rng = np.random.default_rng(seed)
    out = []
    for k, m in enumerate(simulate(SimConfig(motion="random", hand_motion="random", noise="realistic", seed=seed,
                                             duration_s=1.3)).messages(include_truth=False)):
        if m["type"] == "imu" and t0 <= m["t"] < t1:
            gyr = rng.uniform(-6.0, 6.0, 3)
            if k % 37 == 0:
                gyr[k % 3] = GYRO_RANGE_RAD_S * np.sign(gyr[k % 3])
            m = {**m, "gyr": gyr.tolist(), "acc": rng.uniform(-20.0, 20.0, 3).tolist()}
        out.append(parse_message(m))
    return out


def _state(hand: TrackedHand) -> list[np.ndarray]:
    session = hand._session
    together = session._together
    return [session._mount_fits.state, together._x, together._p, together._cx, together._dl, together._pd,
            together._log_r, together._log_g]


def _leaves(value, path=""):
    """Every number and other value of a message, by its path."""
    if isinstance(value, dict):
        for k, v in value.items():
            yield from _leaves(v, f"{path}/{k}")
    elif isinstance(value, list):
        for k, v in enumerate(value):
            yield from _leaves(v, f"{path}/{k}")
    else:
        yield path, value


def _assert_same(a: list, b: list) -> None:
    """The same messages: the same text, or every number within 1e-9 and everything else equal."""
    assert len(a) == len(b)
    for x, y in zip(a, b):
        if json.dumps(x) == json.dumps(y):
            continue
        lx, ly = list(_leaves(x)), list(_leaves(y))
        assert [p for p, _ in lx] == [p for p, _ in ly]
        for (p, u), (_, v) in zip(lx, ly):
            if isinstance(u, float) and isinstance(v, float):
                assert abs(u - v) <= 1e-9 or u == v or (u != u and v != v), (x["t"], p, u, v)
            else:
                assert u == v, (x.get("t"), p, u, v)


def test_the_steady_tick_in_one_call_equals_its_calls_one_by_one(monkeypatch):
    messages = _random_readings(3, 0.8, 1.2)
    steady, early = [], []
    steady_tick = HandSession._steady_tick

    def fused_tick(self, *a):
        # the buffer the kernel writes the corrected readings into is no sensor's last sample before it has
        early.extend(s for s in self._last_sample.values() if s[1] is a[3])
        steady.append(a[4])
        return steady_tick(self, *a)

    monkeypatch.setattr(HandSession, "_steady_tick", fused_tick)
    fused = TrackedHand()
    a = [o for m in messages for o in fused.handle(m)]
    # the random stretch went through the one call, and most ticks before it
    assert sum(0.8 <= t < 1.2 for t in steady) > 60 and len(steady) > 150
    assert not early
    session = fused._session
    # ... and after the kernel every sensor of the tick holds the tick's time and its row of that buffer
    assert all(session._last_sample[s][:2] == (session._processed_t, session._tick_readings) for s in session._tick_ids)
    taken = len(steady)
    monkeypatch.setattr(HandSession, "_advanced_together_again", lambda self: False)
    reference = TrackedHand()
    b = [o for m in messages for o in reference.handle(m)]
    assert len(steady) == taken and len(a) > 100            # the reference took the calls one by one
    _assert_same(a, b)
    for u, v in zip(_state(fused), _state(reference)):
        np.testing.assert_allclose(u, v, rtol=0, atol=1e-9)
    # a kernel checks no bounds: a count of sensor rows or cross-axis offsets that is not the stacked
    # sensors' is refused before the call (the kernel here would only be called if it were not) and before
    # any state moves (δ's clock); a defect of the caller, not a ValueError (the client's bad input)
    together, estimators = session._together, [fs.estimator for fs in session._fingers.values()]
    n, hand, clock = together._gyr.shape[0], session._hand_motion, together._t_dl
    for rows, offsets in ((n - 1, together.cross_offsets), (n, np.zeros((n - 1, 2)))):
        together.cross_offsets = offsets
        with pytest.raises(RuntimeError, match="stacked"):
            together.advance_in(lambda *args: 0.0, (), 1.3, estimators, hand, rows)
        assert together._t_dl == clock


def test_the_steady_tick_cached_code_is_stale_once_a_kernel_it_calls_changes():
    """numba checks only the caller's source file before it loads cached code, and keeps the callees' code
    inside the caller's: the steady tick's index takes the stamp of the files it calls into too."""
    from service import JIT_CACHE
    from service.estimators import chain_kernel
    from service.pipeline import mounting_kernel, tick_kernel

    if not JIT_CACHE:
        pytest.skip("no on-disk kernel cache here")
    from service.estimators.warm import warm
    warm("chain")                                   # compiled into the cache, or loaded from it
    cache_file = tick_kernel.steady_tick._cache._cache_file
    stamp = tick_kernel._sources_stamp(tick_kernel, chain_kernel, mounting_kernel)
    assert cache_file._source_stamp == stamp
    assert cache_file._load_index()
    (t0, size0), (t1, size1), (t2, size2) = stamp
    try:
        cache_file._source_stamp = ((t0, size0), (t1, size1), (t2 + 1.0, size2))     # mounting_kernel.py edited
        assert cache_file._load_index() == {}
    finally:
        cache_file._source_stamp = stamp
