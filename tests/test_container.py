"""The container's promises that can be checked without a container engine (``docker/smoke.sh``
builds and runs the image where docker or podman can): the service runs without the plotting
libraries, the admin token is printed only when generated, compose's settings file is one the
service accepts, and the Dockerfile installs the dependencies before the source."""
import json
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from service.api.config import ServiceSettings
from service.api.server import free_port

pytestmark = pytest.mark.usefixtures("one_hand_worker")     # conftest: one hand worker per service

ROOT = Path(__file__).resolve().parents[1]
BLOCKER = """
import importlib.abc, sys
class NoPlots(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] in ('matplotlib', 'tqdm'):
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
sys.meta_path.insert(0, NoPlots())
"""


def test_every_runtime_module_imports_and_the_service_starts_without_plotting_libraries():
    code = BLOCKER + """
import importlib, pkgutil
import service, gestures, clients
names = [m.name for pkg in (service, gestures, clients)
         for m in pkgutil.walk_packages(pkg.__path__, pkg.__name__ + '.')]
for name in names:
    importlib.import_module(name)
from service.api.app import create_app
from service.api.config import ServiceSettings
create_app(ServiceSettings.load(port=0))
from service.cli import main
print(len(names), main(['bench', 'paper', '--quick', '--out', '/nonexistent']))
"""
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert proc.returncode == 0, proc.stderr
    count, rc = proc.stdout.split()
    assert int(count) > 30 and rc == "2"                      # every module imported; bench paper refused
    assert "needs the 'bench' extra" in proc.stderr and "matplotlib, tqdm" in proc.stderr


def test_runtime_dependencies_leave_out_the_benchmarks_libraries():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    runtime = {re.split(r"[<>=\[ ]", d)[0].lower() for d in project["dependencies"]}
    assert not runtime & {"matplotlib", "tqdm"}
    bench = {re.split(r"[<>=\[ ]", d)[0].lower() for d in project["optional-dependencies"]["bench"]}
    test = {re.split(r"[<>=\[ ]", d)[0].lower() for d in project["optional-dependencies"]["test"]}
    assert bench == {"matplotlib", "tqdm"} and bench <= test


def test_serve_prints_the_admin_token_only_when_it_generated_it(tmp_path):
    admin = "configured-admin-token-0123456789"
    for configured in (True, False):
        cfg = tmp_path / "service.json"
        cfg.write_text(json.dumps({"tokens": {"src-token-c": "source"}, **({"admin_token": admin} if configured else {})}))
        proc = subprocess.Popen([sys.executable, "-m", "service.cli", "serve", "--port", str(free_port()),
                                 "--config", str(cfg)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                cwd=ROOT)
        try:
            lines = [proc.stdout.readline() for _ in range(3)]
        finally:
            proc.terminate()
            proc.wait(timeout=30)
        assert lines[2].startswith("listening on"), lines
        if configured:
            assert admin not in "".join(lines) and "configured" in lines[1] and "not shown" in lines[1]
        else:
            generated = lines[1].rsplit(": ", 1)[1].strip()
            assert lines[1].startswith("admin token (generated, shown once") and len(generated) >= 24


def test_compose_takes_its_settings_from_a_file_the_service_accepts(monkeypatch):
    compose = (ROOT / "docker" / "compose.yaml").read_text()
    assert "${FINGERTRACK_TOKENS" not in compose                 # no interpolation of JSON braces
    assert re.search(r"env_file:\s*\n\s*- fingertrack.env", compose)
    example = (ROOT / "docker" / "fingertrack.env.example").read_text()
    values = dict(line.split("=", 1) for line in example.splitlines() if line and not line.startswith("#"))
    assert set(values) == {"FINGERTRACK_ADMIN_TOKEN", "FINGERTRACK_TOKENS"}
    for key, value in values.items():
        monkeypatch.setenv(key, value)
    settings = ServiceSettings.load()
    assert settings.admin_token == values["FINGERTRACK_ADMIN_TOKEN"]
    assert sorted(grant.role for grant in settings.tokens.values()) == ["source", "viewer"]
    assert "docker/fingertrack.env" in (ROOT / ".gitignore").read_text().splitlines()   # secrets stay out of git


def test_dockerfile_installs_dependencies_before_the_source_and_runs_unprivileged():
    text = (ROOT / "docker" / "Dockerfile").read_text()
    runtime = text[text.rindex("\nFROM "):]                   # the final stage
    assert "PYTHONUNBUFFERED=1" in runtime and "NUMBA_CACHE_DIR=" in runtime
    deps, source = runtime.index("pip install -r"), runtime.index("COPY --from=wheel")
    assert deps < source < runtime.index("\nUSER fingertrack") < runtime.index("fingertrack estimate")
    assert "HEALTHCHECK" in runtime and "--format docker" in text
    ignore = (ROOT / ".dockerignore").read_text().splitlines()
    assert ignore[ignore.index("*") + 1:] and "!service/" in ignore and "!.git" not in ignore


def _smoke(tmp_path, engine_script: str | None):
    """``docker/smoke.sh`` with a PATH that holds only ``dirname`` and, if given, a fake ``docker``."""
    import shutil
    if not (tmp_path / "dirname").exists():
        (tmp_path / "dirname").symlink_to(shutil.which("dirname"))
    if engine_script is not None:
        fake = tmp_path / "docker"
        fake.write_text("#!/bin/sh\n" + engine_script)
        fake.chmod(0o755)
    return subprocess.run([shutil.which("bash"), str(ROOT / "docker" / "smoke.sh")], env={"PATH": str(tmp_path)},
                          capture_output=True, text=True, timeout=60)


def test_the_smoke_test_says_so_when_it_cannot_test_anything_here(tmp_path):
    """Exit 3 with a sentence, not a failure of the image: no engine at all; an engine without the base
    image (offline, nothing in its store)."""
    done = _smoke(tmp_path, None)
    assert done.returncode == 3 and "neither docker nor podman can run containers here" in done.stderr
    done = _smoke(tmp_path, '[ "$1" = info ] && exit 0\nexit 1\n')    # works; has no base image, cannot pull
    assert done.returncode == 3 and "base image python:3.11-slim is neither in its store nor reachable" in done.stderr
    assert "building" not in done.stdout
