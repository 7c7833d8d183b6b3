"""A replay's output does not depend on whether the numba kernels were compiled in the process or loaded
from the on-disk cache: one replay compiles them into an empty cache (its own ``NUMBA_CACHE_DIR``), a
second process loads them from it, and the two outputs are compared byte for byte.

With fused multiply-add allowed (``fastmath={"contract"}``) they differed in the last bits (from the first
steady ticks on): numba puts a copy of each kernel's callees, optimised again, into the caller's code; a
process that compiled the callee runs its own code, one that loaded the caller runs the caller's copy, and
the two copies fused multiply-adds in different places (``service.KERNEL_FASTMATH``)."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from service.sim.session import SimConfig, simulate, write_recording

ROOT = Path(__file__).resolve().parents[1]

REPLAY = """
import json, sys
from service.pipeline.hand import PipelineSettings
from service.pipeline.tracked import replay
from service.protocol import read_recording
recording, out = sys.argv[1], sys.argv[2]
with open(out, "w") as f:
    for name in ("chain", "inertial"):
        for msg in replay((m for _, m in read_recording(recording)), PipelineSettings(estimator=name)):
            f.write(json.dumps(msg, separators=(",", ":")) + "\\n")
"""


def _replay(recording: Path, out: Path, cache: Path) -> bytes:
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache), PYTHONPATH=str(ROOT))
    subprocess.run([sys.executable, "-c", REPLAY, str(recording), str(out)], cwd=ROOT, env=env, check=True,
                   timeout=600)
    return out.read_bytes()


def test_replay_is_the_same_with_a_cold_and_a_warm_kernel_cache(tmp_path):
    recording = tmp_path / "seq.jsonl"
    write_recording(simulate(SimConfig(motion="sequence", noise="realistic", seed=3)), recording)
    cache = tmp_path / "numba"
    cold = _replay(recording, tmp_path / "cold.jsonl", cache)
    assert any(cache.iterdir()), "the first replay wrote no compiled kernels to its cache"
    warm = _replay(recording, tmp_path / "warm.jsonl", cache)
    assert cold.count(b'"type":"frame"') > 1000
    assert cold == warm
