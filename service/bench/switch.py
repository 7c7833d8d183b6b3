"""Estimator-switch stall benchmark: ``fingertrack bench switch [--sessions 4] [--workers N] [--cache
warm|cold|both] [--passes 2] --out DIR``.

The goal it measures: switching a live session to any estimator stalls no other session by more than
10 ms. A fresh service process (``fingertrack serve``, as deployed, with ``--workers`` hand worker
processes; 0 runs the hands on its event loop) receives ``sessions`` simulated hands streamed in real
time by a load-generator process, one subscriber each (``bench.load``'s generator and accounting).
Session ``load-0`` is switched (``PUT /v1/sessions/load-0/config``) through every estimator the service
offers, those with compiled kernels first, then back to the default, ``passes`` times, one switch at a
time with ``gap_s`` of undisturbed streaming before each. The first switch to an estimator with kernels
in a service finds them either absent from the on-disk kernel cache (``cold``: the service starts with a
copy of the cache from which those kernels' modules were removed, so they are compiled, the worst case)
or in it (``warm``: loaded); later switches find them loaded in the process already. A cold run streams ``COLD_LEAD_S`` before its first
switch (a warm one ``LEAD_S``), so that the compile's window has a baseline as long (below).

Per switch, for every *other* session: each frame's delay behind the source's schedule beyond the
pipeline's alignment wait (``bench.load._timing``), over the switch window (from the request to
``SETTLE_S`` after the reply: frames received after the request that were due by the window's end and
after the previous window's end, so that no frame counts in two windows) against the largest of the
frames due in as long just before the request and received before it (at least ``baseline_s``; never
before the previous window's end, nor in the stream's first ``WARMUP_S``: frames due there belong to no
baseline). The stream ends with the last switch's window. The stall is the window's largest delay minus the
baseline's (0 when smaller); a session with no frame in a window or its baseline has no stall figure and
the verdict says the goal was not shown; the largest gap between consecutive frames minus the frame period is
reported beside it. For the switched session: whether the change applied (the reply's estimator), how
long the request took, its own largest delay in the window and how long after the reply its next frame
arrived.

``inject_stop_ms``: with every switch, the service's web process is also stopped (SIGSTOP) that long,
a known stall every session must show: what the benchmark reports for it shows that it can fail.
"""
from __future__ import annotations

import asyncio
import json
import os
import shutil
import signal
import tempfile
import time
from pathlib import Path

import numpy as np

SWITCHED = "load-0"
"""the session that is switched (the generator's first)"""
SETTLE_S = 0.5
"""the switch window goes on this long after the reply, s (the new estimator's first ticks)"""
LEAD_S = 3.0
"""streaming before the first switch with the kernel cache warm, s (the first baseline)"""
COLD_LEAD_S = 30.0
"""streaming before the first switch with the kernel cache cold, s: that switch compiles for 10-20 s, and its
window's largest delay is compared with the largest in as long just before it, as far as the lead reaches (with
3 s, 2 s after the stream's first second: the largest delay of seven times as many frames against it read as a
stall of 6.2 and 14.6 ms in two runs, where 30 s read 0.0 and 10.4 ms)"""
MARGIN_S = 1.0
"""no switch starts later than this before the stream's planned end (plus its window), s"""
WARMUP_S = 1.0
"""the stream's first seconds (sessions starting, the service's first frames) left out of every baseline"""
CACHE_STATES = ("warm", "cold")


def plan(passes: int = 2) -> list[str]:
    """The switched session's estimators in order: every estimator with compiled kernels but the
    default, then the others, then the default, ``passes`` times."""
    from ..estimators.registry import REGISTRY
    from ..pipeline.hand import PipelineSettings

    default = PipelineSettings().estimator
    compiled = [n for n, c in REGISTRY.items() if c.jit_kernels and n != default]
    plain = [n for n in REGISTRY if n != default and n not in compiled]
    return (compiled + plain + [default]) * passes


def kernel_modules(names: list[str]) -> list[tuple[str, str]]:
    """``(cache folder, module file stem)`` of the numba kernels of the estimators ``names``, where this
    process's numba keeps their cache (the service reads the same layout under its ``NUMBA_CACHE_DIR``)."""
    from ..estimators.registry import REGISTRY

    out = []
    for name in names:
        cls = REGISTRY[name]
        for k in getattr(cls, "kernels", ()) if cls.jit_kernels else ():
            out.append((k._cache._cache_path, k.py_func.__module__.rsplit(".", 1)[-1]))
    return sorted(set(out))


def cold_cache(folder: Path, names: list[str]) -> tuple[Path, int]:
    """A copy of the kernel cache in ``folder`` without the cached code of the estimators ``names``'
    kernel modules (every function of those modules: compiled again when first used). Returns the
    copy's path and the number of files removed."""
    from .. import numba_cache_dir

    source = numba_cache_dir()
    if source is None:
        raise ValueError("no writable kernel cache: a cold cache cannot be made (--cache warm runs without one)")
    copy = folder / "numba"
    shutil.copytree(source, copy)
    removed = 0
    for path, stem in kernel_modules(names):
        here = copy / os.path.relpath(path, source)
        for f in here.glob(f"{stem}.*") if here.is_dir() else ():
            f.unlink()
            removed += 1
    return copy, removed


async def _stop_for(pid: int, seconds: float) -> None:
    os.kill(pid, signal.SIGSTOP)
    try:
        await asyncio.sleep(seconds)
    finally:
        os.kill(pid, signal.SIGCONT)


def _switcher(url: str, admin: str, names: list[str], seconds: float, gap_s: float, stop_pid: int | None,
              stop_s: float, lead_s: float):
    """The coroutine function ``bench.load._level`` runs ``lead_s`` into the stream: the switches one at
    a time, until the plan is done or the stream is about to end."""
    from clients.client import rest

    # One request before the stream: the first call imports the HTTP modules (11 ms of CPU, in this
    # process at a higher priority than the niced hand workers), which otherwise fell inside the first
    # switch's window (the first switch stalled every session 12-16 ms in two runs, 6-11 ms with this).
    rest(url, "GET", "/health")

    async def switch_all() -> dict:
        end = time.perf_counter() - lead_s + seconds
        done = []
        for i, name in enumerate(names):
            if i:
                await asyncio.sleep(gap_s)
            if time.perf_counter() + SETTLE_S + MARGIN_S > end:
                break
            sent = time.perf_counter()
            stopper = asyncio.create_task(_stop_for(stop_pid, stop_s)) if stop_pid is not None else None
            status, body = await asyncio.to_thread(rest, url, "PUT", f"/v1/sessions/{SWITCHED}/config", admin,
                                                   {"estimator": name}, timeout_s=600.0)
            returned = time.perf_counter()
            if stopper is not None:
                await stopper
            applied = body.get("estimator") if isinstance(body, dict) else None
            done.append({"estimator": name, "sent": sent, "returned": returned, "status": status,
                         "applied": applied == name, "reply": None if applied == name else str(body)[:300]})
            await asyncio.sleep(SETTLE_S)
        return {"switches": done, "planned": len(names)}
    return switch_all


def _largest_gap(arrivals: np.ndarray, start: float, end: float, past_end: bool = True) -> float | None:
    """The longest time between consecutive frames received in ``[start, end]``, counting from the last
    frame before ``start`` and (``past_end``) to the first after ``end``: a gap that runs past the end
    counts, up to that frame, or to the end when none came; None without two frames."""
    i0 = max(int(np.searchsorted(arrivals, start, side="left")) - 1, 0)
    i1 = int(np.searchsorted(arrivals, end, side="right"))
    part = arrivals[i0:i1]
    if past_end:
        part = arrivals[i0:i1 + 1] if i1 < len(arrivals) else np.append(part, end)
    return float(np.diff(part).max()) if len(part) > 1 else None


def account(switches: list[dict], frames: dict[str, tuple[np.ndarray, np.ndarray]], switched: str,
            period_s: float, settle_s: float = SETTLE_S, baseline_s: float = 1.0) -> list[dict]:
    """Per switch (``{"estimator", "sent", "returned", ...}`` in order, times on the machine's monotonic
    clock), what each session saw; ``frames``: per session, its frames' arrival times (ascending) and
    their delays beyond the schedule (same order), s. Figures in ms (module docstring)."""
    out = []
    firsts = [a[0] - b[0] for a, b in frames.values() if len(a)]
    previous_end = (min(firsts) if firsts else -np.inf) + WARMUP_S     # due times before it: no baseline
    for sw in switches:
        start, end = sw["sent"], sw["returned"] + settle_s
        base_len = max(min(max(baseline_s, end - start), start - previous_end), 0.0)
        row = {**sw, "request_s": sw["returned"] - sw["sent"], "window_s": end - start, "baseline_s": base_len,
               "others": {}}
        for name, (arrivals, beyond) in frames.items():
            due = arrivals - beyond
            inside = (arrivals >= start) & (due <= end) & (due > previous_end)
            before = (due >= start - base_len) & (due > previous_end) & (arrivals < start)
            w = float(beyond[inside].max()) * 1e3 if inside.any() else None
            b = float(beyond[before].max()) * 1e3 if before.any() else None
            gap = _largest_gap(arrivals, start, end)
            gap_b = _largest_gap(arrivals, start - base_len, start, past_end=False)   # the window's own gap is not its
            # the window's two parts: until the reply (the switch itself), after it (the new estimator running)
            part = [beyond[inside & (due <= sw["returned"])], beyond[inside & (due > sw["returned"])]]
            seen = {"frames": int(inside.sum()), "max_delay_ms": w, "baseline_max_delay_ms": b,
                    "stall_ms": None if w is None or b is None else max(0.0, w - b),
                    **{f"stall_{k}_ms": None if b is None or not len(x) else max(0.0, float(x.max()) * 1e3 - b)
                       for k, x in zip(("until_reply", "after_reply"), part)},
                    "largest_gap_minus_period_ms": None if gap is None else 1e3 * (gap - period_s),
                    "baseline_largest_gap_minus_period_ms": None if gap_b is None else 1e3 * (gap_b - period_s)}
            if name == switched:
                later = arrivals[arrivals > sw["returned"]]
                seen["next_frame_after_reply_ms"] = float(later[0] - sw["returned"]) * 1e3 if len(later) else None
                row["switched"] = seen
            else:
                row["others"][name] = seen
        for key in ("stall_ms", "stall_until_reply_ms", "stall_after_reply_ms"):
            stalls = [s[key] for s in row["others"].values() if s[key] is not None]
            row[key] = max(stalls) if stalls else None
        if any(s["stall_ms"] is None for s in row["others"].values()):
            row["stall_ms"] = None
        out.append(row)
        previous_end = end
    return out


def _kernel_state(names: list[str], cache: str) -> list[str]:
    """What each switch in ``names`` finds of its estimator's kernels in the service (module docstring);
    with ``cache`` warm, what the disk cache holds now (before the service starts): kernels missing from it
    are compiled then, and said so."""
    from ..estimators.registry import REGISTRY
    from ..estimators.warm import _kernels, _on_disk
    from ..pipeline.hand import PipelineSettings

    seen = {PipelineSettings().estimator}
    out = []
    for name in names:
        if not REGISTRY[name].jit_kernels:
            out.append("no kernels")
        elif name in seen:
            out.append("loaded")
        elif cache == "cold":
            out.append("compiled (not in the cache)")
        else:
            out.append("loaded from the disk cache" if _on_disk(_kernels(name))
                       else "compiled (not in the cache although warm: warm it first)")
        seen.add(name)
    return out


def run_condition(cache: str = "warm", sessions: int = 4, hand_workers: int | None = None, passes: int = 2,
                  gap_s: float = 2.0, seconds: float | None = None, inject_stop_ms: float | None = None,
                  names: list[str] | None = None, baseline_s: float = 1.0, lead_s: float = LEAD_S) -> dict:
    """One service process, one stream, the switches of ``names`` (default: ``plan(passes)``) in it."""
    from clients.client import rest

    from ..pipeline.hand import PipelineSettings
    from .load import _level
    from .process import service_process

    if cache not in CACHE_STATES:
        raise ValueError(f"cache must be one of {list(CACHE_STATES)}, got {cache!r}")
    names = list(names) if names is not None else plan(passes)
    states = _kernel_state(names, cache)            # before the service fills the cache
    if seconds is None:       # the stream ends with the last switch; at the latest (a compile takes tens of s):
        seconds = lead_s + len(names) * (gap_s + SETTLE_S + 2.0) + (240.0 if cache == "cold" else 0.0) + MARGIN_S
    limits = {"max_sessions": max(64, sessions), "max_sessions_per_token": max(8, sessions),
              "max_connections_per_token": max(32, 2 * sessions),
              **({} if hand_workers is None else {"hand_workers": hand_workers})}
    with tempfile.TemporaryDirectory() as tmp:
        removed, env = 0, None
        if cache == "cold":
            default = PipelineSettings().estimator   # loaded before serving: its kernels stay cached
            copy, removed = cold_cache(Path(tmp), [n for n in dict.fromkeys(names) if n != default])
            env = {"NUMBA_CACHE_DIR": str(copy)}
        with service_process(extra_settings=limits, env=env) as svc:
            def service_cpu():
                own, workers = svc.cpu_seconds(), svc.children_cpu_seconds()
                return None if own is None or workers is None else own + workers
            stop_pid = svc.pid if inject_stop_ms else None
            switcher = _switcher(svc.url, svc.admin, names, seconds, gap_s, stop_pid, (inject_stop_ms or 0) / 1e3, lead_s)
            load_before = os.getloadavg()[0]
            lvl = asyncio.run(_level([svc.url], svc.source, svc.viewer, svc.admin, sessions, 1, seconds, False,
                                     service_cpu, (lead_s, switcher), end_with_kill=True))
            load_after = os.getloadavg()[0]
            _, summaries = rest(svc.url, "GET", "/v1/sessions", svc.admin)
    switches = lvl["killed"].get("switches", [])
    for sw, state in zip(switches, states):
        sw["kernels"] = state
    frames = {}
    for (name, _), rows in lvl["received"].items():
        beyond = np.array(lvl["beyond_by_subscriber"][(name, 0)])
        frames[name] = (np.array([r[0] for r in rows]), beyond)
    period = 1.0 / PipelineSettings().output_rate_hz
    rows = account(switches, frames, SWITCHED, period, baseline_s=baseline_s)
    workers = {x["session"]: (x.get("worker") or {}).get("pid") for x in summaries}
    for row in rows:
        for name, seen in row["others"].items():
            seen["same_worker"] = workers.get(name) is not None and workers.get(name) == workers.get(SWITCHED)
    return {"cache": cache, "sessions": sessions, "hand_workers": "service default" if hand_workers is None else hand_workers,
            "inject_stop_ms": inject_stop_ms, "seconds": seconds, "gap_s": gap_s, "cache_files_removed": removed,
            "planned": len(names), "switches": rows, "frames_period_ms": 1e3 * period,
            "frames_delivered": sum(len(r) for r in lvl["received"].values()),
            "frames_unaccounted": sum(max(0, a["expected"] - a["delivered"] - a["dropped"]) for a in lvl["accounts"].values()),
            "frames_dropped": sum(a["dropped"] for a in lvl["accounts"].values()),
            "source_errors": lvl["errors"], "probe": lvl["probe"],
            "malformed": lvl["malformed"], "malformed_examples": lvl["malformed_examples"],
            "service_cpu_share": None if lvl["service_cpu_s"] is None else lvl["service_cpu_s"] / lvl["wall_s"],
            "generator_cpu_share": lvl["generator_cpu_share"], "load_average_1min": [load_before, load_after]}


def _quantiles(values: list[float]) -> dict | None:
    if not values:
        return None
    a = np.array(values)
    return {"p50": float(np.percentile(a, 50)), "p99": float(np.percentile(a, 99)), "max": float(a.max()), "n": len(a)}


def stall_figures(condition: dict) -> dict:
    """Every other session's stall over every switch of a condition, by what the switch found of its
    kernels, and over all: p50 / p99 / max (ms) and how many."""
    groups: dict[str, list[float]] = {}
    for row in condition["switches"]:
        for seen in row["others"].values():
            if seen["stall_ms"] is not None:
                groups.setdefault(row["kernels"], []).append(seen["stall_ms"])
                groups.setdefault("all", []).append(seen["stall_ms"])
    return {k: _quantiles(v) for k, v in groups.items()}


def _f(v, fmt="{:.1f}") -> str:
    return "-" if v is None else fmt.format(v)


def summary(conditions: list[dict], goal_ms: float = 10.0) -> str:
    """The conditions as Markdown: a table of the switches each, the stalls' quantiles, the verdict."""
    lines = []
    for c in conditions:
        where = "hands on the event loop" if c["hand_workers"] == 0 else f"hand workers: {c['hand_workers']}"
        load = " -> ".join(f"{v:.1f}" for v in c["load_average_1min"])
        stop = f"; the web process stopped {c['inject_stop_ms']:g} ms with every switch" if c["inject_stop_ms"] else ""
        lines += [f"## {c['sessions']} sessions, {where}, kernel cache {c['cache']}"
                  f"{' (' + str(c['cache_files_removed']) + ' cached files removed)' if c['cache'] == 'cold' else ''}"
                  f"{stop}; load average {load}", "",
                  f"{len(c['switches'])} of {c['planned']} planned switches ran; frames delivered {c['frames_delivered']}, "
                  f"dropped {c['frames_dropped']}, unaccounted {c['frames_unaccounted']}, source errors {c['source_errors']}, "
                  f"messages that did not decode or lacked a frame's seq, hand or t {c.get('malformed', 0)}; "
                  f"service CPU {_f(None if c['service_cpu_share'] is None else 100 * c['service_cpu_share'], '{:.0f}')} % "
                  f"of a core, generator {100 * c['generator_cpu_share']:.0f} %.", "",
                  "| # | estimator | its kernels | request, s (window / baseline, s) | applied | other sessions' stall, max ms (same worker) | "
                  "until the reply / after it, ms | "
                  "their largest delay in the window / before it, ms | their largest gap minus the frame period, ms "
                  "(before it) | switched session: largest delay in the window, ms; next frame after the reply, ms |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        for i, row in enumerate(c["switches"], 1):
            others = row["others"].values()
            same = [s["stall_ms"] for s in others if s.get("same_worker") and s["stall_ms"] is not None]
            wmax = max((s["max_delay_ms"] for s in others if s["max_delay_ms"] is not None), default=None)
            bmax = max((s["baseline_max_delay_ms"] for s in others if s["baseline_max_delay_ms"] is not None), default=None)
            gmax = max((s["largest_gap_minus_period_ms"] for s in others
                        if s["largest_gap_minus_period_ms"] is not None), default=None)
            gb = max((s["baseline_largest_gap_minus_period_ms"] for s in others
                      if s["baseline_largest_gap_minus_period_ms"] is not None), default=None)
            sw = row.get("switched", {})
            lines.append(f"| {i} | {row['estimator']} | {row['kernels']} | {row['request_s']:.2f} "
                         f"({row['window_s']:.1f} / {row['baseline_s']:.1f}) | "
                         f"{'yes' if row['applied'] else 'NO: ' + str(row['reply'])} | {_f(row['stall_ms'])}"
                         f" ({_f(max(same) if same else None)}) | {_f(row['stall_until_reply_ms'])} / "
                         f"{_f(row['stall_after_reply_ms'])} | {_f(wmax)} / {_f(bmax)} | {_f(gmax)} ({_f(gb)}) | "
                         f"{_f(sw.get('max_delay_ms'))}; {_f(sw.get('next_frame_after_reply_ms'))} |")
        figures = stall_figures(c)
        lines += ["", "| what the switch found | other sessions' stall p50 / p99 / max, ms (session-switches) |",
                  "|---|---|"]
        for k, q in figures.items():
            lines.append(f"| {k} | {q['p50']:.1f} / {q['p99']:.1f} / {q['max']:.1f} ({q['n']}) |")
        every = figures.get("all")
        unmeasured = sum(s["stall_ms"] is None for row in c["switches"] for s in row["others"].values())
        failed = sum(not row["applied"] for row in c["switches"])
        goal = f"goal (no other session stalled more than {goal_ms:g} ms): "
        if every is not None and every["max"] > goal_ms:
            verdict = goal + f"MISSED (largest stall {every['max']:.1f} ms)"
        elif every is None or unmeasured or failed or len(c["switches"]) < c["planned"]:
            verdict = goal + "NOT SHOWN"
        else:
            verdict = goal + "met"
        short = sum(row["baseline_s"] < row["window_s"] - 1e-9 for row in c["switches"])
        verdict += (f"; {unmeasured} session-switch(es) without a stall figure (no frame in the window or its "
                    f"baseline)" if unmeasured else "") + \
            (f"; {short} switch(es) against a baseline shorter than their window (its largest delay of more frames "
             f"against the baseline's: reads high; a longer --lead for the first)" if short else "") + \
            (f"; {failed} switch(es) not applied" if failed else "")
        probe = c.get("probe") or {}
        health = probe.get("health") or {}
        lines += ["", verdict + (f"; /health p50 / p99 during the run {health['p50_ms']:.1f} / {health['p99_ms']:.1f} ms"
                                 if health.get("p50_ms") is not None else "") + ".", ""]
    lines += ["Stall: per switch and other session, the largest delay of its frames behind the source's schedule "
              "beyond the alignment wait in the switch window (the request until 0.5 s after the reply) minus the "
              "largest of the frames due in as long just before it and received before it (at least 1 s; back to the "
              "previous window's end at most, never the stream's first second), 0 when smaller; a frame counts in one "
              "window at most. "
              "Gap: the longest time between consecutive frames of a session in the window minus the frame period."]
    return "\n".join(lines) + "\n"


def run(out_dir: str | Path, sessions: int = 4, hand_workers: int | None = None, cache: str = "both",
        passes: int = 2, gap_s: float = 2.0, seconds: float | None = None, inject_stop_ms: float | None = None,
        lead_s: float | None = None) -> str:
    """``lead_s``: streaming before the first switch, the baseline of the first (default ``LEAD_S`` with the
    kernel cache warm, ``COLD_LEAD_S`` cold: a compile's window lasts tens of seconds, and a lead as long
    compares it with as long a stretch of undisturbed streaming)."""
    from .process import torn_down_on_signal

    if sessions < 2:
        raise ValueError(f"--sessions must be at least 2 (the switched one and another), got {sessions}")
    if lead_s is not None and lead_s < 1.0:
        raise ValueError(f"--lead must be at least 1 s (the first switch's baseline), got {lead_s:g}")
    if passes < 1:
        raise ValueError(f"--passes must be at least 1, got {passes}")
    if gap_s < 1.0:
        raise ValueError(f"--gap must be at least 1 s (the baseline before each switch), got {gap_s:g}")
    if inject_stop_ms is not None and not 0 < inject_stop_ms < 1e3 * gap_s:
        raise ValueError(f"--inject-stop-ms must be positive and shorter than the gap, got {inject_stop_ms:g}")
    caches = CACHE_STATES if cache == "both" else (cache,)
    if any(c not in CACHE_STATES for c in caches):
        raise ValueError(f"--cache must be warm, cold or both, got {cache!r}")
    leads = {c: lead_s or (COLD_LEAD_S if c == "cold" else LEAD_S) for c in caches}
    longest = max(leads.values())
    if seconds is not None and seconds < longest + SETTLE_S + MARGIN_S:
        raise ValueError(f"--seconds must be at least the lead ({longest:g} s) plus {SETTLE_S + MARGIN_S:g} s for one "
                         f"switch, got {seconds:g}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    with torn_down_on_signal():                 # SIGTERM stops the service and the generator as Ctrl-C does
        try:
            conditions = [run_condition(c, sessions, hand_workers, passes, gap_s, seconds, inject_stop_ms,
                                        lead_s=leads[c]) for c in caches]
        except RuntimeError as err:             # the service or a load generator did not start or failed
            if type(err) is not RuntimeError:   # RecursionError, NotImplementedError: a defect, with its traceback
                raise
            raise ValueError(str(err)) from None
    (out / "results.json").write_text(json.dumps(conditions, indent=2))
    text = summary(conditions)
    (out / "summary.md").write_text(text)
    return text
