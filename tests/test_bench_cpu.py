"""``fingertrack bench cpu`` (quick: one second of data, one pass): it runs the whole recording
through every stage, and once more reading the clock only at its start and end for the total, and writes
what it measured. Its figures go in the README, not into assertions."""
import json

from service.bench import cpu
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
