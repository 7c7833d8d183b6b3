"""The hand pipeline's steady tick in one compiled call (``pipeline/tick_kernel.py``) against the same
calls made one by one (the pipeline's general path, taken when ``_advanced_together_again`` says no):
the same frames, the same fits and filter states. A recording with its faults (dropped samples, a
silent sensor, an occlusion: the general path between steady stretches) is
``tests/test_pipeline.py``'s steady-tick test; here random readings, a clipped gyro among them."""
from __future__ import annotations

import json

import numpy as np
import pytest

from service.estimators.chain import ChainHand
from service.model.units import DEG
from service.pipeline.hand import HandSession
from service.pipeline.tracked import TrackedHand
from service.protocol import encode, parse_message
from service.sim.errors import OpticalModel
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
    # the steady ticks one by one (a run of them in one call, ``_steady_run``, is the next test's)
    monkeypatch.setattr(HandSession, "_steady_run", lambda self, t, given=None: None)
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


def _glove_stream(seed: int, t0: float, t1: float, missing: tuple, gone: float, lost: tuple, duration_s: float = 0.8,
                  metacarpus_every: int = 0, reference: tuple | None = None):
    """A short realistic recording at 1 kHz whose samples arrive in bursts, 20 ticks in one ``imu_batch``
    (so a message releases the ticks of several poses at once, each run of them ended by a frame), with
    random readings between ``t0`` and ``t1`` (a gyro axis at full scale now and then), one sensor's sample
    left out at the ticks ``missing``, the tick ``gone`` left out whole (a step of two ticks) and the optics lost from ``lost[0]`` to ``lost[1]`` s (then back, their
    window filling again). ``metacarpus_every``: a back-of-hand IMU, every so many of its samples kept;
    ``reference``: a reference pose held from ``reference[0]`` to ``reference[1]`` s, sent at the start."""
    rng = np.random.default_rng(seed)
    config = SimConfig(motion="random", hand_motion="random", noise="realistic", seed=seed, duration_s=duration_s,
                       rate_hz=1000.0, optical=OpticalModel(occlusions_s=(lost,)), metacarpus_imu=metacarpus_every > 0)
    out, burst, back_of_hand = [], [], 0
    for k, m in enumerate(simulate(config).messages(include_truth=False)):
        if m["type"] != "imu":
            out.append(parse_message(m))
            if reference is not None and m["type"] == "calibration":
                out.append(parse_message({"type": "reference_pose", "t0": reference[0], "t1": reference[1], "pose": "flat"}))
            continue
        if m["id"] == "metacarpus":
            back_of_hand += 1
            if back_of_hand % metacarpus_every:
                continue
        if (m["id"] == "index.2" and any(abs(m["t"] - u) < 1e-9 for u in missing)) or abs(m["t"] - gone) < 1e-9:
            continue
        if t0 <= m["t"] < t1:
            gyr = rng.uniform(-6.0, 6.0, 3)
            if k % 37 == 0:
                gyr[k % 3] = GYRO_RANGE_RAD_S * np.sign(gyr[k % 3])
            m = {**m, "gyr": gyr.tolist(), "acc": rng.uniform(-20.0, 20.0, 3).tolist()}
        burst.append({key: m[key] for key in ("t", "id", "gyr", "acc")})
        if len(burst) == 200:
            out.append(parse_message({"type": "imu_batch", "samples": burst}))
            burst = []
    return out


def _counted_runs(monkeypatch) -> list:
    """Every ``ChainHand.advance_run`` from now on, as its ticks and how many the kernel did (None: no run)."""
    runs = []
    advance_run = ChainHand.advance_run

    def counted(self, kernel, head, ts, estimators, rows, *scratch):
        out = advance_run(self, kernel, head, ts, estimators, rows, *scratch)
        runs.append((list(ts), None if out is None else out[0]))
        return out

    monkeypatch.setattr(ChainHand, "advance_run", counted)
    return runs


def test_the_steady_ticks_released_together_in_one_call_equal_them_tick_by_tick(monkeypatch):
    missing = (0.345, 0.466)
    # the optics lost from the pose at 0.5333 s on: the frame tick 0.523 (the last of its run) is the first
    # tick this pose covers; their window full again 0.15 s after they are back
    messages = _glove_stream(5, 0.3, 0.5, missing, 0.372, (0.525, 0.565))
    runs = _counted_runs(monkeypatch)
    fused = TrackedHand()
    a = [o for m in messages for o in fused.handle(m)]
    done = [u for ts, n in runs if n for u in ts[:n]]
    # the ticks went through runs, most of nine and more (the random stretch among them), ...
    assert len(done) > 500 and sum(n == len(ts) >= 9 for ts, n in runs) > 40
    assert sum(0.3 <= u < 0.5 for u in done) > 150
    # ... a run ended by the kernel where the optics were lost (the covering pose invalid) and where their
    # window was full again (the tick it left is then processed tick by tick), and no tick missing a
    # sample in one
    cut = [ts[n] for ts, n in runs if n is not None and n < len(ts)]
    assert any(0.52 < u < 0.53 for u in cut) and any(0.565 + 0.13 <= u < 0.565 + 0.17 for u in cut)
    # a run steps over the tick left out whole (the fingers' and δ's steps twice as long there)
    assert any(ts[0] < 0.372 < ts[n - 1] for ts, n in runs if n)
    for u in missing:       # the run before the tick missing a sample ends there, and that tick is in none
        assert any(abs(ts[-1] - (u - 0.001)) < 1e-9 and n == len(ts) >= 4 for ts, n in runs)
        assert not any(abs(u - v) < 1e-9 for v in done)
    session = fused._session
    assert all(session._last_sample[s][:2] == (session._processed_t, session._tick_readings) for s in session._tick_ids)
    # every tick by the calls one by one (the general path)
    monkeypatch.setattr(HandSession, "_advanced_together_again", lambda self: False)
    count = len(runs)
    reference = TrackedHand()
    b = [o for m in messages for o in reference.handle(m)]
    assert len(runs) == count and len(a) > 60
    # the same kernels on the same values: the same bits
    assert [encode(m, False) for m in a] == [encode(m, False) for m in b]
    for u, v in zip(_state(fused) + _clocks(fused), _state(reference) + _clocks(reference)):
        np.testing.assert_array_equal(u, v)


@pytest.mark.parametrize("case", ["reference pose", "back-of-hand IMU"])
def test_a_run_ends_where_a_reference_pose_is_due_and_none_runs_while_the_back_of_hand_imu_is_live(case, monkeypatch):
    """A reference pose due in the middle of a run's ticks ends it there (its tick applies it, as tick by
    tick), and a back-of-hand IMU that is live keeps the ticks out of runs (its sample aids the hand's motion
    at every tick): the same messages, bit for bit, as with no run at all."""
    if case == "reference pose":
        messages = _glove_stream(9, 0.0, 0.0, (), -1.0, (0.9, 0.95), duration_s=0.5, reference=(0.40, 0.4285))
    else:
        messages = _glove_stream(6, 0.0, 0.0, (), -1.0, (0.9, 0.95), duration_s=0.5, metacarpus_every=25)
    runs = _counted_runs(monkeypatch)
    fused = TrackedHand()
    a = [encode(o, False) for m in messages for o in fused.handle(m)]
    assert sum(1 for _, n in runs if n) >= (20 if case == "reference pose" else 2)    # (before the IMU was live)
    if case == "reference pose":
        assert fused._session.counters.references_applied == 1
        assert any(abs(ts[-1] - 0.429) < 1e-9 and n == len(ts) for ts, n in runs)     # a run ended at the tick it is due
    monkeypatch.setattr(HandSession, "_steady_run", lambda self, t, given=None: None)
    reference = TrackedHand()
    assert a == [encode(o, False) for m in messages for o in reference.handle(m)]


def _clocks(hand: TrackedHand) -> list:
    session = hand._session
    return [np.array([session._processed_t, session._tick_t, session._together._t_dl, session._optics_back_t]),
            np.array([fs.estimator._t_last for fs in session._fingers.values()]),
            session._hand_motion.flat, session._tick_readings, session._together._jp, session._together._log_n,
            session._together._log_t[:session._together._log_n.max()]]
