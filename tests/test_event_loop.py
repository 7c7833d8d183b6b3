"""The web process's event loop (``ServiceSettings.event_loop``): Python's asyncio loop by default, uvloop when
told so (or with ``auto`` where it is installed), and a service on either one that serves a glove's frames through
its hand workers to a subscriber and answers ``/health``."""
import asyncio
import json
import os

import pytest

from clients.client import rest
from service.api.config import ServiceSettings, SettingsError, event_loop_name
from service.api.server import ServerThread, uvicorn_config
from test_service import ADMIN, SOURCE, VIEWER, _config, _stream_and_collect

try:
    import uvloop
except ImportError:                                 # (a platform uvloop has no build for)
    uvloop = None


def _settings(**kw) -> ServiceSettings:
    return ServiceSettings.load(port=0, tokens={SOURCE: "source", VIEWER: "viewer"}, admin_token=ADMIN, **kw)


def _serves_frames(srv: ServerThread) -> None:
    """A simulated glove streamed (at 4 x real time) reaches a subscriber as its session's frames, in order."""
    received, pub = asyncio.run(_stream_and_collect(srv, "loop", _config(seed=5)))
    frames = [m for _, m in received if m["type"] == "frame"]
    assert frames and not pub.errors
    assert all(a["seq"] < b["seq"] for a, b in zip(frames, frames[1:]))


@pytest.mark.skipif(uvloop is None, reason="uvloop is not installed here")
def test_auto_runs_on_uvloop_where_it_is_installed():
    settings = _settings(event_loop="auto", hand_workers=0)
    assert event_loop_name(settings) == "uvloop"
    with ServerThread(settings) as srv:
        assert isinstance(srv.app.state.loop, uvloop.Loop)
        assert rest(srv.url, "GET", "/health") == (200, {"status": "ok"})


@pytest.mark.parametrize("told", [False, True])
def test_asyncio_by_default_and_when_told_to(told):
    settings = _settings(**({"event_loop": "asyncio"} if told else {}), hand_workers=0)
    assert event_loop_name(settings) == "asyncio"
    with ServerThread(settings) as srv:
        loop = srv.app.state.loop
        assert type(loop).__module__.startswith("asyncio.") and (uvloop is None or not isinstance(loop, uvloop.Loop))
        assert rest(srv.url, "GET", "/health") == (200, {"status": "ok"})


@pytest.mark.parametrize("name", ["uvloop", "asyncio"])
def test_a_glove_streams_to_a_subscriber_through_the_hand_workers(name):
    """The hand workers' processes and links (subprocesses, a socket pair read by a ``BufferedProtocol``), the
    WebSocket protocol's frame cutting and the frames' writes, on each loop."""
    if name == "uvloop" and uvloop is None:
        pytest.skip("uvloop is not installed here")
    with ServerThread(_settings(event_loop=name, hand_workers=1)) as srv:
        assert type(srv.app.state.loop).__module__.split(".")[0] == name
        _serves_frames(srv)
        _in_a_group_of_its_own_in_this_session(srv.app.state.sessions.pool.links[0].pid)


def _in_a_group_of_its_own_in_this_session(pid: int) -> None:
    """A hand worker leads a process group of its own (a terminal's Ctrl-C to the service's group does not reach
    it) in the web process's session: on Linux with ``sched_autogroup`` a session of its own would be a scheduling
    group of its own, where its nice value no longer yields to the web process."""
    assert os.getpgid(pid) == pid
    assert os.getsid(pid) == os.getsid(0)


def test_uvloop_named_where_it_is_missing_is_a_settings_error(monkeypatch):
    import service.api.config as config
    monkeypatch.setattr(config, "uvloop_installed", lambda: False)
    with pytest.raises(SettingsError, match="event_loop"):
        ServiceSettings.load(event_loop="uvloop")
    assert event_loop_name(ServiceSettings(event_loop="auto")) == "asyncio"
    assert event_loop_name(ServiceSettings()) == "asyncio"


@pytest.mark.parametrize("name", ["uvloop", "asyncio"])
def test_the_setting_reaches_uvicorn(monkeypatch, name):
    if name == "uvloop" and uvloop is None:
        pytest.skip("uvloop is not installed here")
    monkeypatch.setenv("FINGERTRACK_EVENT_LOOP", name)
    settings = ServiceSettings.load()
    config = uvicorn_config(settings, app=object())
    assert config.loop == name
    loop = config.get_loop_factory()()
    try:
        assert type(loop).__module__.split(".")[0] == name
    finally:
        loop.close()
    with pytest.raises(SettingsError, match="event_loop"):
        ServiceSettings.load(event_loop="trio")
    assert json.dumps(settings.masked()["event_loop"]) == f'"{name}"'

