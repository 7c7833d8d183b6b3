"""The service on a read-only root file system, as far as it can be tried without privileges: a real
``fingertrack serve`` process whose numba cache folder, home and (in one case) temporary folder cannot
be written (each lies under a regular file, which no user, root included, can create a folder in)
starts, runs the kernels (a glove's frames reach a subscriber) and writes nothing into the package's
folders (numba, given an unwritable cache folder, used to cache beside the package's source, and a
read-only root file system made that fail at import: "cannot cache function ...: no locator
available"). Every kernel module is imported as always; the sessions run a default estimator without
kernels of its own, so that only the pipeline's kernels are compiled (without a cache, or into a new
one: each case compiles from nothing; ``chain``'s would add 35-40 s of a core to each, and its
kernels are cached by the same numba mechanism, imported with the others). Mounting the root read-only needs privileges a test run may not have; what the service
writes is what such a mount would refuse."""
import asyncio
import os
import subprocess
import sys
from pathlib import Path

import pytest

import clients
import gestures
import service
from clients.client import Publisher, Subscription, wait_healthy
from clients.glove import source_messages
from service.api.server import free_port
from service.sim.session import SimConfig

SOURCE, VIEWER, ADMIN = "src-token-1", "view-token-1", "admin-token-1"
BOUND_S = 900
"""Bounds a failure only: kernels compiled without a cache on a busy machine take minutes."""
PACKAGES = [Path(m.__file__).resolve().parent for m in (service, gestures, clients)]


def _package_files() -> set[Path]:
    """Every file in the package folders but Python's own byte code (which Python skips writing
    where it cannot)."""
    return {p for root in PACKAGES for p in root.rglob("*") if p.is_file() and p.suffix != ".pyc"}


async def _first_frames(url: str, count: int) -> list[dict]:
    frames = []
    sub = Subscription(url, "ro", VIEWER)

    async def collect():
        async for m in sub:
            if m["type"] == "frame":
                frames.append(m)
                if len(frames) == count:
                    return
    task = asyncio.create_task(collect())
    while sub.server_hello is None:
        await asyncio.sleep(0.05)
    pub = Publisher(url, "ro", SOURCE)
    for _, m in source_messages(SimConfig(motion="grasp", noise="white", seed=2, t_m_s=1.0)):
        await pub.send(m)
    await pub.close()                          # every message handled (its sync answered)
    await asyncio.wait_for(task, BOUND_S)
    await sub.close()
    return frames


@pytest.mark.parametrize("temporary", ["writable", "unwritable"])
def test_the_service_serves_with_no_writable_cache_home_or_package(tmp_path, temporary):
    blocked = tmp_path / "a-file"
    blocked.write_text("")
    tmp = tmp_path / "tmp" if temporary == "writable" else blocked / "tmp"
    if temporary == "writable":
        tmp.mkdir()
    port = free_port()
    env = {**os.environ, "NUMBA_CACHE_DIR": str(blocked / "numba"), "HOME": str(blocked / "home"),
           "XDG_CACHE_HOME": str(blocked / "cache"), "TMPDIR": str(tmp), "FINGERTRACK_HAND_WORKERS": "1", "FINGERTRACK_ESTIMATOR": "madgwick",
           "FINGERTRACK_ADMIN_TOKEN": ADMIN, "FINGERTRACK_TOKENS": f'{{"{SOURCE}": "source", "{VIEWER}": "viewer"}}'}
    before = _package_files()
    log = tmp_path / "serve.log"
    with open(log, "w") as out:
        proc = subprocess.Popen([sys.executable, "-m", "service.cli", "serve", "--port", str(port)],
                                cwd=tmp_path, env=env, stdout=out, stderr=subprocess.STDOUT)
    try:
        url = f"http://127.0.0.1:{port}"
        wait_healthy(url, timeout_s=BOUND_S, alive=lambda: proc.poll() is None)
        frames = asyncio.run(_first_frames(url, 5))
    finally:
        proc.terminate()
        proc.wait(timeout=120)
    text = log.read_text()
    assert [f["seq"] for f in frames] == [1, 2, 3, 4, 5]
    assert "Traceback" not in text and "cannot cache" not in text, text
    assert _package_files() - before == set()
    cached = sorted(p.name for p in tmp.rglob("*.nbi")) if temporary == "writable" else []
    if temporary == "writable":                # the kernels were cached in the temporary folder instead
        assert cached, "no kernel cached in the writable temporary folder"
