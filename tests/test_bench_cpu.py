"""``fingertrack bench cpu`` (quick: one second of data, one pass): it runs the whole recording
through every stage, and once more reading the clock only at its start and end for the total, and writes
what it measured. Its figures go in the README, not into assertions."""
import json

import pytest

from service.bench import cpu
from service.pipeline.hand import PipelineSettings
from service.pipeline.tracked import replay
from service.protocol import parse_line


def test_bench_cpu_runs_every_stage_over_the_whole_recording(tmp_path):
    summary = cpu.run(tmp_path, seconds=1.0, repeats=1)
    result = json.loads((tmp_path / "results.json").read_text())
    lines = cpu.recording_lines(1.0)
    frames = sum(m["type"] == "frame" for m in replay(parse_line(line) for line in lines))
    assert result["lines"] == len(lines) and result["frames"] == frames > 60
    assert set(result["runs"][0]) == set(cpu.STAGES) and all(v >= 0 for v in result["runs"][0].values())
    assert len(result["totals"]) == 1 and result["totals"][0] > 0 and len(result["clock_read_cpu_us"]) == 2
    assert "| **total** (clock read per pass) |" in summary and (tmp_path / "summary.md").read_text().startswith(summary)


def test_bench_cpu_runs_the_recording_through_a_hand_worker_too(tmp_path):
    """``--worker``: each repeat also through a hand worker's handling (``Worker.dispatch`` as the web process
    sends the messages): the same frames as the pipeline's passes (it refuses to report otherwise)."""
    summary = cpu.run(tmp_path, seconds=1.0, repeats=1, batched=True, worker=True)
    result = json.loads((tmp_path / "results.json").read_text())
    messages = cpu.worker_messages(cpu.recording_lines(1.0, batched=True))
    assert [m[0] for m in messages[:2]] == ["src", "src"] and {m[0] for m in messages[2:]} == {"chk"}
    assert len(result["worker_totals"]) == 1 and result["worker_totals"][0] > 0 and result["frames"] > 60
    assert result["worker_cpu_s_per_s"]["best"] == result["worker_totals"][0] / result["seconds_of_data"]
    assert "| **in a hand worker**" in summary


class _Kept:
    """A hand worker's end of the web process's socket that keeps every write."""

    def __init__(self):
        self.data = bytearray()

    def sendall(self, data: bytes) -> None:
        self.data += data


def _by_session(data: bytearray) -> dict[int, dict]:
    """What a hand worker wrote, per session: its outputs' texts in order and the numbers of the source
    messages it answered (a ``reps`` run counted as each of its numbers)."""
    from service.api.hands.worker import whole_batches

    sessions: dict[int, dict] = {}
    for batch in whole_batches(data):
        for m in batch:
            s = sessions.setdefault(m[1], {"out": [], "answered": []})
            if m[0] == "out":
                s["out"].append(m[4])
            elif m[0] == "rep":
                s["answered"].append(m[2])
            elif m[0] == "reps":
                s["answered"] += range(m[2], m[3] + 1)
    return sessions


def test_bench_cpu_runs_n_sessions_in_one_hand_worker(tmp_path):
    """``--hands``: per N, N sessions' streams through one hand worker; each session makes the frames of its
    recording (the same in every pass), so N sessions make N times one's, and one session the pipeline's."""
    summary = cpu.run(tmp_path, seconds=2.0, repeats=1, batched=True, hands=(1, 4))
    result = json.loads((tmp_path / "results.json").read_text())
    one, four = result["hands"]
    assert (one["hands"], four["hands"]) == (1, 4) and one["frames"] == result["frames"] > 100
    assert four["frames"] == 4 * one["frames"]
    assert four["hand_seconds_timed"] == 4 * (2.0 - cpu.FIRST_S) and len(four["cpu_s"]) == 1 and four["cpu_s"][0] > 0
    assert four["cpu_ms_per_hand_s"]["best"] == 1e3 * four["cpu_s"][0] / four["hand_seconds_timed"]
    assert four["to_one_hand"]["best"] == four["cpu_ms_per_hand_s"]["best"] / one["cpu_ms_per_hand_s"]["best"]
    assert "| 4 | " in summary and "to one hand" in summary


def test_the_n_hand_pass_gives_each_session_what_it_gets_alone():
    """Interleaved in one worker (in writes grouped every ``GROUP_S``), every session gets the outputs of its
    recording alone, in order, and every one of its source messages is answered once."""
    recordings = [cpu.timed_recording(1.5, seed) for seed in range(4)]
    together = _Kept()
    _, frames = cpu._pass_hands(recordings, PipelineSettings(), sock=together)
    got = _by_session(together.data)
    assert sorted(got) == [1, 2, 3, 4] and min(frames) > 100
    for sid, recording in enumerate(recordings, 1):
        alone = _Kept()
        _, (count,) = cpu._pass_hands([recording], PipelineSettings(), sock=alone)
        assert count == frames[sid - 1]
        assert got[sid]["out"] == _by_session(alone.data)[1]["out"]
        assert sorted(got[sid]["answered"]) == list(range(len(recording)))


def test_the_web_process_writes_as_it_groups_them():
    """``worker_batches``: every message once, in order of arrival; with ``GROUP_SESSIONS`` sessions or more
    the writes at least ``GROUP_S`` apart, each message in the first write at or after its arrival; with fewer,
    a write per arrival time."""
    from service.api.hands.pool import GROUP_S

    recordings = [cpu.timed_recording(0.3, seed) for seed in range(4)]
    for n in (2, 4):
        stream = cpu.interleaved(recordings[:n])
        assert [t for t, _ in stream] == sorted(t for t, _ in stream)
        batches = cpu.worker_batches(stream, n)
        assert [m for _, batch in batches for m in batch] == [m for _, m in stream]
        arrivals = iter(t for t, _ in stream)
        previous = float("-inf")
        for due, batch in batches:
            times = [next(arrivals) for _ in batch]
            assert previous < max(times) <= due
            if n >= 4:
                assert due - previous >= GROUP_S - 1e-12
            else:
                assert set(times) == {due}
            previous = due


def test_bench_cpu_measures_a_sessions_start(tmp_path):
    """``--starts``: per session its construction, first second and steady second; its data's four parts make
    the frames of its whole recording, and the first second's excess is its first minus its steady second."""
    summary = cpu.run(tmp_path, seconds=1.0, repeats=1, starts=2)
    s = json.loads((tmp_path / "results.json").read_text())["starts"]
    assert s["sessions"] == 2 and len(s["frames"]) == 2 and all(len(f) == 4 for f in s["frames"])
    for seed, parts in enumerate(s["frames"]):
        _, (whole,) = cpu._pass_hands([cpu.timed_recording(cpu.STEADY_S[1], seed)], PipelineSettings())
        assert sum(parts) == whole and parts[0] > 60 and parts[2] > 60
    per = s["per_session"]
    assert all(v > 0 for v in per["construct_ms"] + per["first_second_ms"] + per["steady_second_ms"])
    assert per["excess_ms"] == pytest.approx([a - b for a, b in zip(per["first_second_ms"], per["steady_second_ms"])])
    assert s["mean"]["excess_ms"] == pytest.approx(s["mean"]["first_second_ms"] - s["mean"]["steady_second_ms"])
    assert "first second's excess" in summary
