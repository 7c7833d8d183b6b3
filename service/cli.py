"""The ``fingertrack`` command line. Presentation only: the work happens in the library modules."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from .sim.errors import NOISE_KINDS
from .sim.motions import FINGER_MOTIONS, HAND_MOTIONS


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not np.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive finite number, got {text!r}")
    return value


def _cmd_simulate(args: argparse.Namespace) -> int:
    from .sim.session import SimConfig, simulate, write_recording

    config = SimConfig(motion=args.motion, t_m_s=args.tm, hand=args.hand, hand_motion=args.hand_motion,
                       noise=args.noise, seed=args.seed, rate_hz=args.rate)
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


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="fingertrack", description="Finger tracking for VR hand interaction.")
    sub = parser.add_subparsers(dest="command", required=True)

    sim = sub.add_parser("simulate", help="simulate a glove + optical tracker and write a protocol-v1 recording")
    sim.add_argument("--motion", choices=sorted(FINGER_MOTIONS), default="grasp", help="finger motion (default grasp)")
    sim.add_argument("--tm", type=_positive_float, default=None, help="movement duration t_m in seconds")
    sim.add_argument("--noise", choices=NOISE_KINDS, default="both", help="IMU errors (default both)")
    sim.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    sim.add_argument("--rate", type=_positive_float, default=200.0, help="IMU rate in Hz (default 200)")
    sim.add_argument("--hand", choices=("right", "left"), default="right")
    sim.add_argument("--hand-motion", choices=sorted(HAND_MOTIONS), default="still", help="metacarpus trajectory (default still)")
    sim.add_argument("--no-truth", action="store_true", help="leave out the truth messages")
    sim.add_argument("--out", required=True, help="output recording, JSON Lines")
    sim.set_defaults(func=_cmd_simulate)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except (ValueError, OSError) as err:
        print(f"fingertrack {args.command}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
