"""The ``fingertrack`` command line. Presentation only: the work happens in the library modules."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from .api.config import describe_validation_error
from .sim.errors import NOISE_KINDS
from .sim.motions import FINGER_MOTIONS, HAND_MOTIONS

REPLAY_SHOWN_ERRORS = 10
"""Bad lines of a recording printed one by one; the rest are counted."""


def _number(cast: type, low: float, strict: bool, expected: str):
    """An argparse type: a finite ``cast`` (``int`` or ``float``) at or above ``low`` (above, if
    ``strict``); the error names what was expected and what was given."""
    def parse(text: str):
        try:
            value = cast(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {'a whole number' if cast is int else 'a number'}, got {text!r}") from None
        if not np.isfinite(value) or value < low or (strict and value == low):
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
        return value
    return parse


_positive_float = _number(float, 0.0, True, "a positive finite number")
_non_negative_float = _number(float, 0.0, False, "a non-negative finite number")
_positive_int = _number(int, 1, False, "a positive whole number")
_non_negative_int = _number(int, 0, False, "a non-negative whole number")


def _service_url(text: str) -> str:
    """The service's address: http(s) or ws(s) with a host (``clients.client.service_url``)."""
    from clients.client import service_url
    try:
        return service_url(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def _interval(text: str) -> tuple[float, float]:
    try:
        a, b = (float(x) for x in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected START:END in seconds, got {text!r}") from None
    if not (np.isfinite(a) and np.isfinite(b)) or b <= a:
        raise argparse.ArgumentTypeError(f"expected START:END with END > START, got {text!r}")
    return a, b


def _count_list(text: str) -> tuple[int, ...]:
    """``1,2,4`` -> (1, 2, 4): positive whole numbers."""
    try:
        return tuple(_positive_int(x.strip()) for x in text.split(","))
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"expected comma-separated positive whole numbers like 1,2,4, got {text!r}") from None


def _cmd_simulate(args: argparse.Namespace) -> int:
    from .sim.session import SimConfig, simulate, write_recording

    from .sim.errors import OpticalModel

    optical = None
    if args.occlusion or args.optical_rate is not None or args.latency is not None:
        base = OpticalModel.perfect() if args.noise == "none" else OpticalModel()
        optical = OpticalModel(rate_hz=args.optical_rate or base.rate_hz,
                               latency_s=base.latency_s if args.latency is None else args.latency,
                               position_jitter_m=base.position_jitter_m, orientation_jitter_rad=base.orientation_jitter_rad,
                               occlusions_s=tuple(args.occlusion))
    config = SimConfig(motion=args.motion, t_m_s=args.tm, hand=args.hand, hand_motion=args.hand_motion,
                       noise=args.noise, seed=args.seed, rate_hz=args.rate, optical=optical,
                       reference_hold_s=args.reference_pose or 0.0, metacarpus_imu=args.metacarpus_imu)
    session = simulate(config)
    out = Path(args.out)
    if out.parent and not out.parent.exists():
        out.parent.mkdir(parents=True)
    count = write_recording(session, out, include_truth=not args.no_truth)
    duration = session.t[-1] - session.t[0]
    print(f"wrote {out}: {count} messages, {duration:.3f} s, {len(session.t)} IMU samples x "
          f"{len(session.sensor_ids)} sensors at {args.rate:g} Hz, {len(session.pose_t)} poses at "
          f"{session.optical.rate_hz:g} Hz")
    print(f"motion={args.motion} hand={args.hand} hand-motion={args.hand_motion} noise={args.noise} seed={args.seed}")
    print("joint angle range, degrees (min .. max):")
    for finger, phi in session.joint_angles.items():
        names = session.calibration.finger(finger).joint_names
        cells = "  ".join(f"{n} {np.degrees(phi[:, j].min()):6.1f} .. {np.degrees(phi[:, j].max()):6.1f}"
                          for j, n in enumerate(names))
        print(f"  {finger:<7} {cells}")
    return 0


def _parse_params(pairs: list[str]) -> dict:
    """``NAME=VALUE`` pairs to settings keyword arguments; a dotted name reaches a nested settings
    object (``core.tau_acc_s=2`` for the ``inertial`` estimator's core). Values stay strings: the
    settings models validate and convert them."""
    params: dict = {}
    for pair in pairs:
        if "=" not in pair:
            raise ValueError(f"--param expects NAME=VALUE, got {pair!r}")
        name, value = pair.split("=", 1)
        *path, leaf = [part.strip() for part in name.split(".")]
        if not leaf or not all(path):
            raise ValueError(f"--param: empty name in {pair!r}")
        node = params
        for part in path:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ValueError(f"--param: {name!r} sets a field inside {part!r}, which is also given a value")
        if isinstance(node.get(leaf), dict):
            raise ValueError(f"--param: {name!r} is a group of settings, set its fields as {name}.FIELD=VALUE")
        node[leaf] = value.strip()
    return params


def _service_arguments(parser: argparse.ArgumentParser, role: str) -> None:
    """``--url`` and ``--token`` of a command that connects to a running service."""
    parser.add_argument("--url", required=True, type=_service_url, help="service URL, e.g. http://127.0.0.1:8765")
    parser.add_argument("--token", required=True, help=f"a token with the {role} role")


def _estimator_arguments(parser: argparse.ArgumentParser) -> None:
    """``--estimator NAME`` and its settings: ``--param NAME=VALUE`` (``_parse_params``); ``--beta B``
    is short for ``--param beta=B`` (Madgwick's gain)."""
    parser.add_argument("--estimator", default="chain", help="estimator name (fingertrack estimate --list; default chain)")
    parser.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                        help="any estimator setting; NAME.FIELD for a nested one (e.g. core.tau_acc_s=2)")
    parser.add_argument("--beta", dest="param", action="append", type=lambda value: f"beta={value}", metavar="B",
                        help="the same as --param beta=B: the madgwick estimator's gain, rad/s")


def _cmd_estimate(args: argparse.Namespace) -> int:
    from .estimators.registry import REGISTRY, EstimatorSpec, make_estimator

    if args.list:
        for name, cls in REGISTRY.items():
            doc = (sys.modules[cls.__module__].__doc__ or "").strip().splitlines()
            print(f"{name}\t{doc[0] if doc else ''}")
        return 0
    if not args.recording or not args.out:
        raise ValueError("estimate needs a recording and --out (or --list)")
    from pydantic import ValidationError

    from .model.hand import joint_to_phalanx_angles
    from .estimators.base import finger_mode
    from .pipeline.hand import PipelineSettings
    from .pipeline.offline import load_recording, run_with_references

    try:
        spec = EstimatorSpec.of(args.estimator, _parse_params(args.param))
    except ValidationError as err:
        raise ValueError(describe_validation_error(err, f"estimator {args.estimator!r} setting")) from None
    rec = load_recording(args.recording)
    rows = []
    report = []
    for finger, geom in rec.calibration.fingers.items():
        if not rec.instrumented(finger):
            report.append(f"  {finger:<7} untracked: no sensors or no complete IMU sample")
            continue
        samples, dropped = rec.finger_samples(finger)
        truth = rec.truth_angles(finger, samples.t)
        initial = None
        if args.init_from_truth:
            if truth is None:
                raise ValueError("--init-from-truth: the recording has no truth for every sample")
            initial = joint_to_phalanx_angles(truth[0])
        track = run_with_references(make_estimator(spec, geom, initial_theta=initial), samples, finger,
                                    rec.references, PipelineSettings().reference_pose_std_rad)
        for k in range(len(track.t)):
            phi = track.phi[k]
            cells = [f"{v:.9g}" for v in phi] + [""] * (3 - len(phi))
            rows.append(f"{track.t[k]:.9g},{finger},{','.join(cells)},{finger_mode(track.mode[k])}")
        if args.truth:
            if truth is None:
                report.append(f"  {finger:<7} no truth in the recording")
            else:
                rms = np.degrees(np.sqrt(np.mean((track.phi - truth) ** 2, axis=0)))
                cells = "  ".join(f"{n} {v:7.3f}" for n, v in zip(geom.joint_names, rms))
                report.append(f"  {finger:<7} {cells}")
        if dropped:
            report.append(f"  {finger:<7} {dropped} incomplete IMU ticks dropped")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("t,finger,mcp,pip,dip,mode\n" + "\n".join(rows) + "\n")
    print(f"wrote {out}: {len(rows)} rows, estimator {args.estimator}")
    if report:
        if args.truth:
            print("RMS error per joint, degrees:")
        print("\n".join(report))
    return 0


def _cmd_replay(args: argparse.Namespace) -> int:
    import json

    from pydantic import ValidationError

    from .estimators.registry import EstimatorSpec
    from .pipeline.hand import PipelineSettings
    from .pipeline.tracked import replay
    from .protocol import read_recording

    try:
        settings = PipelineSettings(estimator=args.estimator, estimator_params=_parse_params(args.param))
        EstimatorSpec.of(settings.estimator, settings.estimator_params)
    except ValidationError as err:
        raise ValueError(describe_validation_error(err, f"estimator {args.estimator!r} setting")) from None
    bad = good = 0

    def skipped(number, err) -> None:
        nonlocal bad
        bad += 1
        if bad <= REPLAY_SHOWN_ERRORS:
            print(f"{args.recording}:{number}: skipped: {err.code}: {err.detail[:200]}", file=sys.stderr)

    def messages():
        nonlocal good
        for _, message in read_recording(args.recording, on_error="skip", skipped=skipped):
            good += 1
            yield message

    counts: dict[str, int] = {}
    events = []
    out = open(args.out, "w", encoding="utf-8") if args.out else None
    try:
        for msg in replay(messages(), settings):
            counts[msg["type"]] = counts.get(msg["type"], 0) + 1
            if msg["type"] == "gesture":
                events.append(msg)
            if out:
                out.write(json.dumps(msg, separators=(",", ":")) + "\n")
    finally:
        if out:
            out.close()
    if bad > REPLAY_SHOWN_ERRORS:
        print(f"{args.recording}: ... and {bad - REPLAY_SHOWN_ERRORS} more bad lines", file=sys.stderr)
    if good == 0:
        raise ValueError(f"{args.recording} is not a recording: none of its {bad} lines is a protocol-v1 message")
    print(f"replayed {args.recording} with {args.estimator}: {counts.get('frame', 0)} frames, "
          f"{len(events)} gesture events, {bad} bad lines skipped" + (f"; wrote {args.out}" if args.out else ""))
    for ev in events:
        print(f"  t={ev['t']:8.3f}  {ev['gesture']:<6} {ev['event']:<5} confidence {ev['confidence']:.2f}")
    return 0


def _cmd_serve(args: argparse.Namespace) -> int:
    from .api.app import create_app
    from .api.config import ServiceSettings, event_loop_name
    from .api.server import FingertrackServer, listen_socket, serving_gc, uvicorn_config
    from .api.stacks import stacks_on_signal

    stacks_on_signal()                                  # kill -USR1: every thread's stack into the log
    if args.bus is not None:
        _need_nats_extra()
    loaded = ServiceSettings.load(args.config, host=args.host, port=args.port, bus=args.bus)
    sock = listen_socket(loaded.host, loaded.port)      # the port is checked before anything is printed
    if loaded.bus is not None and not _wait_for_bus(loaded.bus):
        return 130
    settings = loaded.with_admin_token()
    print("fingertrack service settings:", settings.masked(), flush=True)
    if loaded.admin_token:
        print("admin token: the configured one (FINGERTRACK_ADMIN_TOKEN or the settings file), not shown", flush=True)
    else:
        print(f"admin token (generated, shown once; set FINGERTRACK_ADMIN_TOKEN to choose one): {settings.admin_token}",
              flush=True)
    print(f"listening on http://{settings.host}:{sock.getsockname()[1]} (viewer at /viewer/, docs at /docs; "
          f"event loop {event_loop_name(settings)})", flush=True)
    app = create_app(settings)
    with serving_gc():
        FingertrackServer(uvicorn_config(settings, app)).run(sockets=[sock])
    return 0


def _wait_for_bus(url: str) -> bool:
    """Wait until the NATS server answers (each failed attempt is one log line), before uvicorn takes
    over SIGINT and SIGTERM: its startup would wait for the connection for ever and ignore both. False
    if interrupted."""
    import asyncio

    from .bus.subjects import close, connect

    async def probe():
        await close(await connect(url, "fingertrack-gateway"))
    try:
        asyncio.run(probe())
    except KeyboardInterrupt:
        return False
    return True


def _need_nats_extra() -> None:
    try:
        import nats  # noqa: F401
    except ImportError:
        raise SystemExit("--bus needs the optional extra 'nats': pip install -e '.[nats]'") from None


def _cmd_worker(args: argparse.Namespace) -> int:
    _need_nats_extra()
    import asyncio

    from .api.config import ServiceSettings
    from .bus.worker import run_worker

    settings = ServiceSettings.load(args.config, bus=args.bus)
    try:
        asyncio.run(run_worker(args.bus, settings, args.id))
    except ConnectionError as err:
        raise SystemExit(f"fingertrack worker: {err}") from None
    return 0


def _cmd_glove(args: argparse.Namespace) -> int:
    import asyncio

    from clients.glove import stream_glove
    from .sim.session import SimConfig

    config = SimConfig(motion=args.motion, t_m_s=args.tm, hand=args.hand, noise=args.noise, seed=args.seed,
                       rate_hz=args.rate, hand_motion=args.hand_motion, reference_hold_s=args.reference_pose or 0.0,
                       metacarpus_imu=args.metacarpus_imu)

    async def run():
        pub = await stream_glove(args.url, args.session, args.token, config)
        await pub.close()
        return pub
    pub = asyncio.run(run())
    print(f"streamed {args.motion} to {args.url} session {args.session}; {len(pub.errors)} error replies, "
          f"{pub.reconnects} reconnects")
    for e in list(pub.errors)[:10]:
        print(f"  error {e['code']}: {e['detail']}")
    return 0


def _cmd_watch(args: argparse.Namespace) -> int:
    import asyncio

    from clients.client import Subscription
    from clients.demo import angles_line

    async def run():
        last = -1e9
        count = 0
        async for msg in Subscription(args.url, args.session, args.token):
            if msg["type"] == "gesture":
                print(f"gesture {msg['gesture']} {msg['event']} t={msg['t']:.3f} confidence {msg['confidence']:.2f}")
            elif msg["type"] == "frame" and msg["t"] - last >= args.every:
                last = msg["t"]
                print(angles_line(msg))
            count += 1
            if args.count and count >= args.count:
                return
    try:
        asyncio.run(run())
    except KeyboardInterrupt:
        pass
    return 0


def _session_hand(text: str) -> tuple[str, str]:
    """``NAME`` or ``NAME:HAND`` -> (name, hand); the hand defaults to right."""
    name, _, hand = text.partition(":")
    hand = hand or "right"
    if not name or hand not in ("right", "left"):
        raise argparse.ArgumentTypeError(f"expected NAME or NAME:HAND with HAND right or left, got {text!r}")
    return name, hand


def _cmd_lsl(args: argparse.Namespace) -> int:
    import asyncio

    from websockets.exceptions import InvalidStatus

    from clients.client import Refused
    from clients.lsl import LslBridge

    try:
        bridge = LslBridge(args.url, args.token, args.session, source_clock=args.source_clock, rate_hz=args.rate,
                           binary=args.binary)
    except RuntimeError as err:                     # pylsl or liblsl missing
        raise ValueError(str(err)) from None
    for name, streams in bridge.streams.items():
        for hand in streams.hands:
            print(f"LSL stream 'fingertrack {name} {hand}' (MoCap, 14 joint angles, rad) source_id "
                  f"{bridge.source_id(name, hand)}")
        print(f"LSL stream 'fingertrack {name} gestures' (Markers) source_id {bridge.source_id(name, 'gestures')}")
    print(f"republishing from {args.url} (source clock: {args.source_clock}); Ctrl-C stops")
    try:
        asyncio.run(bridge.run())
    except Refused as err:                          # "URL: HTTP 403[: detail]" or a close reason
        reason = str(err).split(": ", 1)[-1]
        raise ValueError(f"the service refused the subscription: {reason}"
                         + ("; --token needs the viewer role" if reason == "HTTP 403" else "")) from None
    except InvalidStatus as err:
        reason = err.response.body.decode(errors="replace").strip()
        raise ValueError(f"the service refused the subscription: HTTP {err.response.status_code}"
                         + (f" {reason}" if reason else "; --token needs the viewer role")) from None
    except KeyboardInterrupt:
        pass
    for name, streams in bridge.streams.items():
        print(f"session {name}: {streams.frames} frames, {streams.events} gesture events republished")
    return 0


def _cmd_schema(args: argparse.Namespace) -> int:
    from .protocol import PROTOCOL_VERSION
    from .protocol.schema import documents, dump, write_documents

    if args.out is None:
        print(dump({"protocol": PROTOCOL_VERSION, "documents": documents()}), end="")
        return 0
    written = write_documents(args.out)
    print(f"wrote {len(written)} documents to {args.out}: " + ", ".join(p.name for p in written))
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from clients.demo import run_demo
    return run_demo()


def _need_bench_extra() -> None:
    """The benchmarks that draw figures or progress bars need the 'bench' extra (not in the service image)."""
    import importlib
    missing = []
    for lib in ("matplotlib", "tqdm"):
        try:
            importlib.import_module(lib)
        except ImportError:
            missing.append(lib)
    if missing:
        raise ValueError(f"this benchmark needs the 'bench' extra (pip install 'fingertrack[bench]'); "
                         f"missing: {', '.join(missing)}")


def _cmd_bench(args: argparse.Namespace) -> int:
    if args.which in ("paper", "peers", "gestures", "load", "accuracy"):
        _need_bench_extra()
    if args.which == "paper":
        from .bench import paper
        print(paper.run(args.out, quick=args.quick, seeds=args.seeds, workers=args.workers))
        print(f"\nwrote {args.out}/results.csv, summary.md, fig10.png, fig9.png")
        return 0
    if args.which == "peers":
        from .bench import peers
        if not args.data:
            raise ValueError("bench peers needs --data DIR (a folder of BROAD .mat trials)")
        print(peers.run(args.data, args.out, quick=args.quick))
        print(f"wrote {args.out}/results.csv, summary.md, peers.png")
        return 0
    if args.which == "latency":
        from .bench import latency
        print(latency.run(args.out, seconds=args.seconds or 20.0, imu_rate_hz=args.imu_rate, hand_workers=args.hand_workers))
        print(f"wrote {args.out}/results.json, summary.md")
        return 0
    if args.which == "load":
        from .bench import load
        if args.bus is not None:
            _need_nats_extra()
        print(load.run(args.out, hands=args.hands, subscribers=args.subscribers, seconds=args.seconds,
                       binary=args.binary, bus_workers=args.workers if args.bus else None,
                       kill_at_s=args.kill_worker_at, hand_workers=None if args.bus else args.workers,
                       gateways=args.gateways, generators=args.generators,
                       **({} if args.metrics_every is None else {"metrics_every_s": args.metrics_every})))
        print(f"wrote {args.out}/results.json, summary.md")
        return 0
    if args.which == "switch":
        from .bench import switch
        print(switch.run(args.out, sessions=args.sessions, hand_workers=args.workers, cache=args.cache,
                         passes=args.passes, gap_s=args.gap, seconds=args.seconds, inject_stop_ms=args.inject_stop_ms,
                         lead_s=args.lead))
        print(f"wrote {args.out}/results.json, summary.md")
        return 0
    if args.which == "robustness":
        from .bench import robustness
        print(robustness.run(args.out, quick=args.quick, messages=args.messages, soak_seconds=args.soak_seconds))
        print(f"wrote {args.out}/summary.md, results.csv, results.json, fuzz.csv, extremes.csv, soak.csv, logs/")
        return 0
    if args.which == "accuracy":
        from .bench import accuracy
        print(accuracy.run(args.out, quick=args.quick, trials=args.trials, workers=args.workers,
                           duration_s=args.seconds, first_seed=args.first_seed))
        print(f"wrote {args.out}/results.csv, events.csv, results.json, summary.md, accuracy.png")
        return 0
    if args.which == "cpu":
        from .bench import cpu
        from pydantic import ValidationError

        from .estimators.registry import EstimatorSpec
        params = _parse_params(args.param)
        try:
            EstimatorSpec.of(args.estimator, params)
        except ValidationError as err:
            raise ValueError(describe_validation_error(err, f"estimator {args.estimator!r} setting")) from None
        print(cpu.run(args.out, seconds=args.seconds, repeats=args.repeats, estimator=args.estimator,
                      params=params, profile=args.profile, batched=args.batch, worker=args.worker,
                      hands=args.hands or (), starts=args.starts or 0))
        print(f"wrote {args.out}/results.json, summary.md" + (", profile.txt" if args.profile else ""))
        return 0
    if args.which == "gestures":
        from .bench import gestures
        print(gestures.run(args.out, quick=args.quick, workers=args.workers, cache_dir=args.frames_cache,
                            trials=args.trials, idle_trials=args.idle_trials))
        print(f"wrote {args.out}/results.json, summary.md")
        return 0
    raise ValueError(f"unknown benchmark {args.which!r}")


def _gesture_idle_plan(quick: bool) -> dict:
    from .bench import gestures
    return gestures.QUICK_IDLE if quick else gestures.FULL_IDLE


def _gesture_enrolment_s() -> float:
    """Length of the enrolment procedure before each gesture trial, s."""
    from .sim import gesture_script as gs
    return len(gs.ENROLMENT_ORDER) * (gs.ENROLMENT_HOLD_S + gs.ENROLMENT_TRANSITION_S)


def _gesture_plan(quick: bool) -> dict:
    from .bench import gestures
    return gestures.QUICK if quick else gestures.FULL


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="fingertrack", description="Finger tracking for VR hand interaction.")
    sub = parser.add_subparsers(dest="command", required=True)

    sim = sub.add_parser("simulate", help="simulate a glove + optical tracker and write a protocol-v1 recording")
    sim.add_argument("--motion", choices=sorted(FINGER_MOTIONS), default="grasp", help="finger motion (default grasp)")
    sim.add_argument("--tm", type=_positive_float, default=None, help="movement duration t_m in seconds")
    sim.add_argument("--noise", choices=NOISE_KINDS, default="both", help="IMU errors (default both)")
    sim.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    sim.add_argument("--rate", type=_positive_float, default=200.0, help="IMU rate in Hz (default 200)")
    sim.add_argument("--hand", choices=("right", "left"), default="right", help="which hand (default right)")
    sim.add_argument("--hand-motion", choices=sorted(HAND_MOTIONS), default="still", help="metacarpus trajectory (default still)")
    sim.add_argument("--optical-rate", type=_positive_float, default=None, help="optical pose rate in Hz (default 90)")
    sim.add_argument("--latency", type=_non_negative_float, default=None, help="optical latency in s (default 0.02)")
    sim.add_argument("--occlusion", type=_interval, action="append", default=[], metavar="START:END",
                     help="optics occluded (valid: false) from START to END seconds; repeatable")
    sim.add_argument("--no-truth", action="store_true", help="leave out the truth messages")
    sim.add_argument("--reference-pose", type=_positive_float, default=None, metavar="SECONDS",
                     help="hold the hand flat this long first and record a reference_pose message")
    sim.add_argument("--metacarpus-imu", action="store_true",
                     help="the glove also has an IMU on the back of the hand (sensor id metacarpus)")
    sim.add_argument("--out", required=True, help="output recording, JSON Lines")
    sim.set_defaults(func=_cmd_simulate)

    est = sub.add_parser("estimate", help="run a recording through an estimator and write joint angles as CSV (offline: "
                                          "the hand's motion from all poses at once, each finger alone, so chain takes "
                                          "neither the hand's shared acceleration error nor the gyros' angle that "
                                          "the live pipeline and replay give it; their frames differ)")
    est.add_argument("recording", nargs="?", help="protocol-v1 recording, JSON Lines")
    _estimator_arguments(est)
    est.add_argument("--list", action="store_true", help="list the estimators, one per line, name first")
    est.add_argument("--truth", action="store_true", help="print RMS error per joint in degrees (needs truth)")
    est.add_argument("--init-from-truth", action="store_true", help="start from the recording's true initial configuration")
    est.add_argument("--out", help="output CSV: t,finger,mcp,pip,dip,mode (radians)")
    est.set_defaults(func=_cmd_estimate)

    rep = sub.add_parser("replay", help="run a recording through the hand pipeline and gesture recogniser")
    rep.add_argument("recording", help="protocol-v1 recording, JSON Lines")
    _estimator_arguments(rep)
    rep.add_argument("--out", help="write the frames and gesture events as JSON Lines")
    rep.set_defaults(func=_cmd_replay)

    srv = sub.add_parser("serve", help="run the tracking service (FastAPI + uvicorn)")
    srv.add_argument("--host", default=None, help="listen address (default 127.0.0.1)")
    srv.add_argument("--port", type=int, default=None, help="TCP port (default 8765)")
    srv.add_argument("--config", default=None, help="settings file (JSON object); environment FINGERTRACK_* also applies")
    srv.add_argument("--bus", default=None, help="NATS URL (nats://HOST:PORT): run as a gateway; sessions run in "
                     "'fingertrack worker' processes (needs the extra 'nats')")
    srv.set_defaults(func=_cmd_serve)

    wrk = sub.add_parser("worker", help="run hand workers that own sessions of gateways on a NATS bus")
    wrk.add_argument("--bus", required=True, help="NATS URL, nats://HOST:PORT (JetStream enabled)")
    wrk.add_argument("--id", default=None, help="worker name (default: generated)")
    wrk.add_argument("--config", default=None, help="settings file (estimator, output rate, record_dir ...); FINGERTRACK_* applies")
    wrk.set_defaults(func=_cmd_worker)

    glv = sub.add_parser("glove", help="stream a simulated glove + optical tracker to a service in real time")
    _service_arguments(glv, "source")
    glv.add_argument("--session", default="default", help="session to stream into (default default)")
    glv.add_argument("--motion", choices=sorted(FINGER_MOTIONS), default="sequence",
                     help="finger motion (default sequence: point, grasp, release, pinch, open)")
    glv.add_argument("--tm", type=_positive_float, default=None,
                     help="movement duration t_m in seconds (default: the motion's own)")
    glv.add_argument("--hand", choices=("right", "left"), default="right", help="which hand (default right)")
    glv.add_argument("--rate", type=_positive_float, default=200.0, help="IMU rate in Hz (default 200)")
    glv.add_argument("--noise", choices=NOISE_KINDS, default="both", help="IMU errors (default both)")
    glv.add_argument("--hand-motion", choices=sorted(HAND_MOTIONS), default="still",
                     help="metacarpus trajectory (default still)")
    glv.add_argument("--seed", type=int, default=0, help="random seed of the sensor errors (default 0)")
    glv.add_argument("--reference-pose", type=_positive_float, default=None, metavar="SECONDS",
                     help="hold the hand flat this long first and send a reference_pose message when done")
    glv.add_argument("--metacarpus-imu", action="store_true",
                     help="also stream an IMU on the back of the hand (sensor id metacarpus)")
    glv.set_defaults(func=_cmd_glove)

    wat = sub.add_parser("watch", help="subscribe and print gesture events and live joint angles")
    _service_arguments(wat, "viewer")
    wat.add_argument("--session", default="default", help="session to watch (default default)")
    wat.add_argument("--every", type=_positive_float, default=0.25, help="seconds between angle lines (default 0.25)")
    wat.add_argument("--count", type=int, default=0, help="stop after this many messages (default 0: never)")
    wat.set_defaults(func=_cmd_watch)

    lsl = sub.add_parser("lsl", help="republish sessions as Lab Streaming Layer streams (joint angles, gesture markers)",
                         description="Subscribe to sessions of a running service and republish each hand as an LSL "
                                     "stream (type MoCap, one channel per joint angle in radians, stable source_id) "
                                     "and its gesture events as an LSL marker stream, for LabRecorder and any LSL "
                                     "inlet. Needs pylsl: pip install 'fingertrack[lsl]'. Runs until Ctrl-C.")
    _service_arguments(lsl, "viewer")
    lsl.add_argument("--session", type=_session_hand, action="append", required=True, metavar="NAME[:HAND]",
                     help="a session to republish, with the hand its source is (right or left; default right); "
                          "repeatable")
    lsl.add_argument("--source-clock", choices=("estimate", "lsl"), default="estimate",
                     help="how frame times map to the LSL clock: 'lsl' if the source stamps with this machine's "
                          "monotonic clock (the LSL clock), else 'estimate': source time plus the smallest delay "
                          "seen (default estimate)")
    lsl.add_argument("--rate", type=_positive_float, default=90.0,
                     help="nominal rate of the hand streams, Hz: the service's frame rate (default 90)")
    lsl.add_argument("--binary", action="store_true", help="subscribe with MessagePack instead of JSON")
    lsl.set_defaults(func=_cmd_lsl)

    sch = sub.add_parser("schema", help="write the JSON Schema of every protocol-v1 message and the AsyncAPI document",
                         description="JSON Schema (draft 2020-12) of every protocol-v1 message, one file each plus "
                                     "the unions source-message and service-message, and asyncapi.json for the two "
                                     "WebSockets; generated from the protocol models (the copies in docs/schema/ are "
                                     "the same; the service serves them at /v1/schema).")
    sch.add_argument("--out", default=None, metavar="DIR",
                     help="write one file per document into DIR (default: print them all as one JSON object)")
    sch.set_defaults(func=_cmd_schema)

    demo = sub.add_parser("demo", help="the service, a simulated glove and a subscriber, end to end (~10 s)")
    demo.set_defaults(func=_cmd_demo)

    bench = sub.add_parser("bench", help="benchmarks: the paper's experiment, gestures, real data against peer "
                                         "libraries, service latency, CPU per hand, service load, robustness, "
                                         "accuracy in use, estimator switch",
                           description="Each benchmark has its own options: fingertrack bench NAME --help.")
    which = bench.add_subparsers(dest="which", required=True, metavar="NAME")

    def benchmark(name: str, help: str, description: str) -> argparse.ArgumentParser:
        b = which.add_parser(name, help=help, description=description)
        b.add_argument("--out", required=True, metavar="DIR", help="output folder (created if missing)")
        b.set_defaults(func=_cmd_bench)
        return b

    b = benchmark("paper", "the paper's experiment: grasp motions, three error series, every estimator",
                  "Section 3 of the paper: grasp motions with t_m log-spaced from 0.1 s to 1000 s (32 durations), "
                  "white-noise, zero-offset and both error series at MPU-9250 figures, every estimator; writes "
                  "results.csv, summary.md, fig10.png, fig9.png.")
    b.add_argument("--quick", action="store_true",
                   help="6 durations from 0.1 s to 31.6 s and one seed instead of 32 up to 1000 s")
    b.add_argument("--seeds", type=_positive_int, default=5,
                   help="noise seeds per duration and series (default 5; --quick uses 1)")
    b.add_argument("--workers", type=_positive_int, default=2, help="worker processes (default 2)")

    b = benchmark("gestures", "gesture recognition scored against what the visitor means",
                  "Simulated people (hand size, coupling, gesture styles) doing an enrolment and then random scripts of "
                  "gestures and meaningless distractors, realistic IMU errors, through the live pipeline; scored "
                  "against the scripted intents (F1, confusion, false activations per minute, latency from the "
                  "intended moment, ray error, chatter) with default and enrolled thresholds, the vector estimator, "
                  "the true hand and the true hand plus 5 deg; writes results.json, summary.md.")
    quick, full = _gesture_plan(True), _gesture_plan(False)
    quick_idle, full_idle = _gesture_idle_plan(True), _gesture_idle_plan(False)
    b.add_argument("--quick", action="store_true",
                   help=f"{len(quick['seeds'])} trials of {quick['duration_s']:g} s and {len(quick_idle['seeds'])} idle "
                        f"of {quick_idle['duration_s']:g} s instead of {len(full['seeds'])} of {full['duration_s']:g} s and "
                        f"{len(full_idle['seeds'])} idle of {full_idle['duration_s']:g} s (each gesture trial after a "
                        f"{_gesture_enrolment_s():.0f} s enrolment)")
    b.add_argument("--workers", type=_positive_int, default=2, help="worker processes (default 2)")
    b.add_argument("--trials", type=_positive_int, default=None,
                   help="only the first N trials of the run (default: all)")
    b.add_argument("--idle-trials", type=_non_negative_int, default=None,
                   help=f"only the first N idle trials (the visitor means nothing, scored for false activations; "
                        f"default: all, {len(full_idle['seeds'])} in the full run, {len(quick_idle['seeds'])} with --quick)")
    b.add_argument("--frames-cache", default=None, metavar="DIR",
                   help="keep each trial's pipeline frames in DIR and reuse them, so recogniser changes are rescored "
                        "without rerunning the pipeline (a trial is rerun when the code that makes its frames "
                        "changes; default: none)")

    b = benchmark("peers", "real rigid-IMU data (BROAD): our orientation cores against vqf, ahrs, imufusion",
                  "Inclination error on the BROAD trials against their optical ground truth, and time per sample, "
                  "for our rigid cores and the peer libraries (pip install -e '.[peers]'); writes results.csv, "
                  "summary.md, peers.png.")
    b.add_argument("--data", required=True, metavar="DIR", help="folder of BROAD .mat trials")
    b.add_argument("--quick", action="store_true",
                   help="the first 20000 samples of the first three trials instead of every trial in full")

    b = benchmark("latency", "service latency: glove to subscriber, in a fresh service process",
                  "A simulated hand streams in real time into a fresh service process; for every frame a "
                  "subscriber receives, the time since the glove sent the message that completed it; writes "
                  "results.json, summary.md.")
    b.add_argument("--seconds", type=_positive_float, default=20.0, help="streaming time, s (default 20)")
    b.add_argument("--imu-rate", type=_positive_float, default=200.0, metavar="HZ",
                   help="IMU sample rate of the glove, Hz (default 200); each tick is one imu_batch message")
    b.add_argument("--hand-workers", type=_non_negative_int, default=None, metavar="N",
                   help="the service's hand worker processes (default: the service's default; 0: hands on its event loop)")

    b = benchmark("cpu", "CPU time of one hand, stage by stage (parse, pipeline, encode), in one process",
                  "A realistic simulated one-hand recording through parsing, the hand pipeline with gestures and the "
                  "JSON encoding of every output, in this process; CPU seconds per second of data (process time, "
                  "not wall time), best and median of the passes; writes results.json, summary.md.")
    b.add_argument("--seconds", type=_positive_float, default=20.0, help="length of the recording, s (default 20)")
    b.add_argument("--repeats", type=_positive_int, default=3, help="timed passes (default 3)")
    _estimator_arguments(b)         # e.g. --param implementation=reference: chain's numpy reference
    b.add_argument("--profile", action="store_true", help="also write cProfile's top functions of one pipeline pass")
    b.add_argument("--batch", action="store_true",
                   help="each tick's IMU samples in one imu_batch message, as the glove streams them (default: one "
                        "imu message per sample, as in a recording)")
    b.add_argument("--worker", action="store_true",
                   help="also run each pass through a hand worker's handling of its session's messages (validation, "
                        "pipeline, encoding and framing of its outputs, as the web process sends them), its total apart")
    b.add_argument("--hands", type=_count_list, default=None, metavar="N,...",
                   help="also run N sessions in one hand worker per pass, for each N given (e.g. 1,4,12): their glove "
                        "streams (one seed each) interleaved in order of arrival and written to the worker as the web "
                        "process writes them; each session's first second not timed; CPU ms per hand and second of data")
    b.add_argument("--starts", type=_positive_int, default=None, metavar="SESSIONS",
                   help="also start SESSIONS sessions one after another, each alone in a hand worker: CPU of its "
                        "hand's construction (as on open), its first second of data and a steady second (its third)")

    b = benchmark("load", "service load: several hands at once, subscribers per hand",
                  "Hands streamed at once into a fresh service process per load level, with subscribers per hand: "
                  "every frame accounted for, order and session integrity, backlog and service CPU; writes "
                  "results.json, summary.md.")
    b.add_argument("--hands", type=_count_list, default=(1, 2, 4),
                   help="comma-separated numbers of hands streamed at once, one level each (default 1,2,4)")
    b.add_argument("--subscribers", type=_positive_int, default=2, help="subscribers per hand (default 2)")
    b.add_argument("--seconds", type=_positive_float, default=20.0, help="streaming time per load level, s (default 20)")
    b.add_argument("--binary", action="store_true", help="MessagePack instead of JSON")
    b.add_argument("--bus", choices=("nats",), default=None,
                   help="run the service as a gateway and --workers hand workers on a local nats-server "
                        "(default: one service process)")
    b.add_argument("--workers", type=_non_negative_int, default=2,
                   help="hand worker processes: the service's (0: its hands on the event loop) or, with --bus nats, "
                        "the bus's (default 2)")
    b.add_argument("--gateways", type=_positive_int, default=1, help="with --bus nats: gateway processes; each "
                   "session's glove and subscribers are spread over them (default 1)")
    b.add_argument("--kill-worker-at", type=_positive_float, default=None, metavar="S",
                   help="kill (SIGKILL) the hand worker owning most sessions S seconds into the stream (default: none)")
    b.add_argument("--generators", type=_positive_int, default=None, metavar="N",
                   help="load-generator processes for the gloves and subscribers (default: one per 50 hands, bench.load.GENERATOR_HANDS)")
    b.add_argument("--metrics-every", type=_positive_float, default=None, metavar="S",
                   help="the probe's time between two GET /metrics, s (default 1; GET /health every 0.05 s; "
                        "0.05 asks for both in every round, as before)")

    b = benchmark("switch", "estimator switch: how long a live session's switch stalls the other sessions",
                  "Sessions stream in real time into a fresh service process, one subscriber each; one session is "
                  "switched through every estimator (PUT /v1/sessions/{s}/config), with the compiled ones' kernels "
                  "absent from the cache (cold) or in it (warm); per switch, the other sessions' frames' delay in the "
                  "switch window against just before it; writes results.json, summary.md.")
    b.add_argument("--sessions", type=_positive_int, default=4, help="sessions streaming at once, one switched (default 4)")
    b.add_argument("--workers", type=_non_negative_int, default=None,
                   help="the service's hand worker processes (default: the service's default; 0: hands on its event loop)")
    b.add_argument("--cache", choices=("warm", "cold", "both"), default="both",
                   help="the compiled estimators' kernels in the disk cache (warm), removed from a copy of it (cold), "
                        "or one service each (both, the default)")
    b.add_argument("--passes", type=_positive_int, default=2, help="times through every estimator (default 2)")
    b.add_argument("--gap", type=_positive_float, default=2.0, metavar="S",
                   help="undisturbed streaming before each switch, s (default 2)")
    b.add_argument("--seconds", type=_positive_float, default=None,
                   help="longest streaming time per service (default: enough for the plan, 240 s more with a cold "
                        "cache); the stream ends with the last switch")
    b.add_argument("--lead", type=_positive_float, default=None, metavar="S",
                   help="streaming before the first switch, its baseline, s (default 3 with the cache warm, 30 cold: "
                        "a compile's window lasts 10-20 s and is compared with as long a stretch before it)")
    b.add_argument("--inject-stop-ms", type=_positive_float, default=None, metavar="MS",
                   help="also stop the service's web process (SIGSTOP) this long with every switch: a known stall "
                        "the figures must show")

    b = benchmark("robustness", "hostile input, extremes, slow readers, connection storms, kill -9, soak",
                  "A robustness campaign against fresh service processes: fuzzing, schema-valid extremes in a "
                  "live stream, never-reading subscribers, a connection storm, kill -9 while recording and a soak, "
                  "each beside a good session; writes summary.md, results.csv, results.json and the logs.")
    b.add_argument("--quick", action="store_true",
                   help="1500 fuzz messages, 2 s of extremes on two probes, 2 readers, 100 connects, one kill and a "
                        "5 s soak instead of 100000 messages, 6 s on every probe, 5 readers, 2000 connects, three "
                        "kills and a 600 s soak")
    b.add_argument("--messages", type=_positive_int, default=None,
                   help="hostile messages in the fuzz (default 100000; 1500 with --quick)")
    b.add_argument("--soak-seconds", type=_positive_float, default=None,
                   help="length of the soak, s (default 600; 5 with --quick)")

    b = benchmark("accuracy", "accuracy where the glove is really used: realistic errors, live pipeline, no true start",
                  "Seeded trials of realistic use through the live pipeline: the realistic error profile, random "
                  "gesture scripts with fast transitions, a rotating or reaching hand, sensor dropouts, an optical "
                  "occlusion, a flat-hand hold with and without its reference_pose; every estimator side by side; "
                  "writes results.csv, events.csv, results.json, summary.md, accuracy.png.")
    b.add_argument("--quick", action="store_true",
                   help="one 6 s trial with chain, ekf and vector, one coupling trial and one back-of-hand IMU trial with "
                        "chain, instead of 5 trials of 12 s with every estimator, 4 coupling trials with chain and ekf "
                        "and 5 back-of-hand IMU trials")
    b.add_argument("--trials", type=_positive_int, default=None, help="seeded trials (default 5; --quick 1)")
    b.add_argument("--seconds", type=_positive_float, default=None, help="length of each trial, s (default 12; --quick 6)")
    b.add_argument("--workers", type=_positive_int, default=2, help="worker processes (default 2)")
    b.add_argument("--first-seed", type=_non_negative_int, default=0,
                   help="seed of the first trial (default 0, the published figures); tune settings on trials from "
                        "another seed (e.g. 500) so the scored trials stay unseen")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except KeyboardInterrupt:
        return 130
    except (ValueError, OSError) as err:  # ProtocolError and SettingsError are ValueErrors
        for line in str(err).splitlines() or [type(err).__name__]:
            print(f"fingertrack {args.command}: error: {line}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
