"""Hand geometry and calibration: fingers, phalanx lengths, base frames and sensor placement.

The metacarpus frame is the frame of the optical ``pose.orientation`` (DESIGN.md): origin at the
wrist joint centre, ``x`` the hinge axis of the long fingers, ``y`` toward the fingers, ``z`` palmar.
Each finger has a base frame (its zero-flexion finger frame, paper section 2.1) placed at its MCP
joint; the long fingers' base frames are parallel to the metacarpus frame.

Default geometry: an average adult hand of length 0.19 m (wrist crease to middle fingertip; the
comparison paper's subjects measured 19.4 ± 1.1 cm). Phalanx and metacarpal lengths are the
segment-length / hand-length ratios of Buchholz, Armstrong & Goldstein (1992), "Anthropometric data
for describing the kinematics of the human hand", Ergonomics 35(3):261-273. MCP spacing across the
hand (20 mm) is an average adult value; treat it as an approximation, calibrate for precision.

Thumb simplification: the thumb is a planar two-link chain (proximal and distal phalanx, joints MCP
and IP) hinged on a fixed base frame; the carpometacarpal joint and its opposition motion are not
modelled (the thumb metacarpal is treated as part of the rigid metacarpus).

Left hands are the mirror image of right hands through the metacarpus yz-plane: base positions get
``x -> -x`` and base orientations ``R -> S R S`` with ``S = diag(-1, 1, 1)``. The finger-frame
convention (``x = y × z``) is the same for both hands, so flexion stays positive.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass, field, replace
from typing import Literal, Mapping

import numpy as np
from scipy.spatial.transform import Rotation

from .frames import MIRROR_X, matrix_to_quat, quat_to_matrix
from .units import DEG

Hand = Literal["right", "left"]
FINGERS: tuple[str, ...] = ("thumb", "index", "middle", "ring", "little")
LONG_FINGERS: tuple[str, ...] = ("index", "middle", "ring", "little")
HAND_LENGTH_M = 0.19
"""Default hand length (wrist crease to middle fingertip), metres."""

# Buchholz et al. (1992), segment length / hand length: (metacarpal, proximal, middle, distal).
_BUCHHOLZ_RATIOS = {
    "thumb": (0.251, 0.196, None, 0.158),
    "index": (0.374, 0.265, 0.143, 0.097),
    "middle": (0.373, 0.277, 0.170, 0.108),
    "ring": (0.336, 0.259, 0.165, 0.107),
    "little": (0.295, 0.206, 0.117, 0.093),
}
_MCP_X_RIGHT_M = {"index": 0.030, "middle": 0.010, "ring": -0.010, "little": -0.030}
"""MCP joint positions across the right hand (metacarpus x, toward the thumb), metres."""

# Thumb base frame in the metacarpus frame (right hand): its long axis turned 45 deg toward the
# thumb side (about the metacarpus z), then rolled 40 deg about that axis so that flexion sweeps the
# tip across the palm toward the index fingertip. An approximation of the opposed resting thumb,
# chosen so that a pinch (index MCP/PIP/DIP 40 deg, thumb MCP 40, IP 30 deg) brings the tips within
# 12 mm and an open hand holds them 88 mm apart.
_THUMB_BASE_ROTATION = Rotation.from_euler("ZY", [-45.0, -40.0], degrees=True)
_THUMB_BASE_POSITION_RIGHT_M = (0.030, 0.050, 0.025)

JOINT_LIMITS_RAD: dict[str, tuple[tuple[float, float], ...]] = {
    # (min, max) per joint; after Hume et al. (1990) and common clinical active ranges of motion.
    "long": ((-30 * DEG, 90 * DEG), (-5 * DEG, 110 * DEG), (-10 * DEG, 90 * DEG)),
    "thumb": ((-10 * DEG, 60 * DEG), (-20 * DEG, 85 * DEG)),
}
"""Anatomical joint limits, rad: long fingers (MCP, PIP, DIP), thumb (MCP, IP)."""


def joint_limits(finger: str) -> tuple[tuple[float, float], ...]:
    return JOINT_LIMITS_RAD["thumb" if finger == "thumb" else "long"]


JOINT_NAMES_LONG = ("mcp", "pip", "dip")
JOINT_NAMES_THUMB = ("mcp", "ip")


_MATRICES: dict[bytes, np.ndarray] = {}
"""``rotation_matrix``'s matrices by their quaternion's bits."""


def rotation_matrix(q_xyzw) -> np.ndarray:
    """``quat_to_matrix`` of one ``[x, y, z, w]`` placement (a mounting, a base orientation): computed once per
    exact value (its four numbers' bits, so ``-0.0`` is not ``0.0``) and handed out as a new array each call."""
    try:
        key = struct.pack("4d", *q_xyzw)
    except (struct.error, TypeError):
        return quat_to_matrix(np.asarray(q_xyzw))
    kept = _MATRICES.get(key)
    if kept is None:
        if len(_MATRICES) >= 1024:
            _MATRICES.clear()
        kept = _MATRICES[key] = quat_to_matrix(np.asarray(q_xyzw))
    return kept.copy()


class FrozenFingers(dict):
    """The fingers of a shared calibration (``default_calibration``, ``HandCalibration.with_overrides``): every
    hand on that calibration holds the same object, so it refuses to be changed in place (a changed
    calibration is a new one: ``with_overrides``, ``dataclasses.replace``)."""

    def _refuse(self, *args, **kwargs):
        raise TypeError("a shared calibration's fingers are not changed in place; make a new calibration "
                        "(HandCalibration.with_overrides)")

    __setitem__ = __delitem__ = clear = pop = popitem = setdefault = update = __ior__ = _refuse

    def __reduce__(self):
        return FrozenFingers, (dict(self),)


@dataclass(frozen=True)
class SensorPlacement:
    """One IMU on a phalanx.

    Attributes:
        id: sensor id ``<finger>.<phalanx>`` (DESIGN.md).
        phalanx: index of the phalanx it sits on (0 proximal).
        offset_m: distance from the phalanx's proximal joint along the phalanx, metres (paper ``p_k``).
        mounting: ``[x, y, z, w]`` rotation of the sensor frame in the phalanx frame (identity:
            sensor axes = phalanx axes).
    """

    id: str
    phalanx: int
    offset_m: float
    mounting: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)

    def mounting_matrix(self) -> np.ndarray:
        return rotation_matrix(self.mounting)


METACARPUS_SENSOR_ID = "metacarpus"
"""Sensor id of the optional IMU on the back of the hand (fixed to the metacarpus)."""


@dataclass(frozen=True)
class MetacarpusImu:
    """The optional IMU on the back of the hand (sensor id ``metacarpus``), rigidly on the metacarpus.

    Attributes:
        position_m: the sensor's position in the metacarpus frame, metres (default: the middle of the
            back of the hand, 5 cm from the wrist toward the fingers and 1.5 cm dorsal, ``-z``).
        mounting: ``[x, y, z, w]`` rotation of the sensor frame in the metacarpus frame.
    """

    position_m: tuple[float, float, float] = (0.0, 0.05, -0.015)
    mounting: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)

    def mounting_matrix(self) -> np.ndarray:
        return rotation_matrix(self.mounting)


@dataclass(frozen=True)
class FingerGeometry:
    """Planar chain of one finger (paper section 2.1).

    Attributes:
        name: finger name.
        lengths_m: phalanx lengths ``l_0..l_{n-1}``, metres (3 for long fingers, 2 for the thumb).
        base_position_m: MCP joint in the metacarpus frame, metres.
        base_orientation: ``[x, y, z, w]`` zero-flexion finger frame in the metacarpus frame.
        coupling: ``φ_{k+1} = coupling · φ_k`` closes the chain where a joint is not measured
            (paper section 2.2: DIP equals PIP, ``coupling = 1``), dimensionless.
        sensors: IMUs on this finger.
    """

    name: str
    lengths_m: tuple[float, ...]
    base_position_m: tuple[float, float, float]
    base_orientation: tuple[float, float, float, float]
    coupling: float
    sensors: tuple[SensorPlacement, ...]

    @property
    def n_phalanges(self) -> int:
        return len(self.lengths_m)

    @property
    def joint_names(self) -> tuple[str, ...]:
        return JOINT_NAMES_THUMB if self.n_phalanges == 2 else JOINT_NAMES_LONG

    def base_matrix(self) -> np.ndarray:
        return rotation_matrix(self.base_orientation)

    def sensor(self, sensor_id: str) -> SensorPlacement:
        for s in self.sensors:
            if s.id == sensor_id:
                return s
        raise KeyError(f"finger {self.name!r} has no sensor {sensor_id!r}")


@dataclass(frozen=True)
class HandCalibration:
    """Geometry of one hand: the five fingers keyed by name."""

    hand: Hand
    fingers: Mapping[str, FingerGeometry] = field(default_factory=dict)

    def finger(self, name: str) -> FingerGeometry:
        try:
            return self.fingers[name]
        except KeyError:
            raise KeyError(f"unknown finger {name!r}; expected one of {FINGERS}") from None

    @property
    def sensor_ids(self) -> tuple[str, ...]:
        return tuple(s.id for f in self.fingers.values() for s in f.sensors)

    def with_overrides(self, fingers: Mapping[str, Mapping]) -> "HandCalibration":
        """Apply a protocol-v1 ``calibration`` message's ``fingers`` object; every field optional.

        Raises ``ValueError`` naming the finger and field when a value is inconsistent.

        Applied to a shared calibration (``default_calibration``, or one this returned), overrides of plain
        values (a parsed message's: dicts, lists, strings, numbers) give a shared calibration too: the same
        object for the same calibration and overrides, whose fingers' constants are then built once for all
        the hands on it (``estimators.observations``, ``pipeline.mounting``).
        """
        key = (id(self), _exact_text(fingers)) if _SHARED.get(id(self)) is self else None
        if key is not None and key[1] is not None:
            kept = _OVERRIDDEN.get(key)
            if kept is not None:
                return kept
            if len(_OVERRIDDEN) >= 256:
                _OVERRIDDEN.clear()
            _OVERRIDDEN[key] = out = _shared(self._overridden(fingers))
            return out
        return self._overridden(fingers)

    def _overridden(self, fingers: Mapping[str, Mapping]) -> "HandCalibration":
        new = dict(self.fingers)
        for name, over in fingers.items():
            if name not in FINGERS:
                raise ValueError(f"calibration: unknown finger {name!r}; expected one of {FINGERS}")
            new[name] = _override_finger(self.finger(name), over)
        return replace(self, fingers=new)


def _override_finger(geom: FingerGeometry, over: Mapping) -> FingerGeometry:
    changes: dict = {}
    if over.get("lengths") is not None:
        lengths = tuple(float(v) for v in over["lengths"])
        if len(lengths) != geom.n_phalanges:
            raise ValueError(
                f"calibration.fingers.{geom.name}.lengths: expected {geom.n_phalanges} values, got {len(lengths)}"
            )
        if any(not (0.0 < v < 0.2) for v in lengths):
            raise ValueError(
                f"calibration.fingers.{geom.name}.lengths: phalanx lengths must be in (0, 0.2) m, got {list(lengths)}"
            )
        changes["lengths_m"] = lengths
    base = over.get("base")
    if base is not None:
        if base.get("position") is not None:
            changes["base_position_m"] = tuple(float(v) for v in base["position"])
        if base.get("orientation") is not None:
            q = np.asarray(base["orientation"], dtype=float)
            norm = np.linalg.norm(q)
            if abs(norm - 1.0) > 1e-12:   # renormalise what the protocol's tolerance let through
                q = q / norm
            changes["base_orientation"] = tuple(float(v) for v in q)
    if over.get("coupling") is not None:
        changes["coupling"] = float(over["coupling"])
    if over.get("sensors") is not None:
        sensors = []
        lengths = changes.get("lengths_m", geom.lengths_m)
        for i, s in enumerate(over["sensors"]):
            ph = int(s["phalanx"])
            where = f"calibration.fingers.{geom.name}.sensors[{i}]"
            if not 0 <= ph < len(lengths):
                raise ValueError(f"{where}.phalanx: expected 0..{len(lengths) - 1}, got {ph}")
            offset = float(s.get("offset", 0.5 * lengths[ph]))
            if not 0.0 <= offset <= lengths[ph]:
                raise ValueError(f"{where}.offset: must lie on the phalanx, 0..{lengths[ph]} m, got {offset}")
            mounting = tuple(float(v) for v in s.get("mounting", (0.0, 0.0, 0.0, 1.0)))
            sensors.append(SensorPlacement(str(s["id"]), ph, offset, mounting))  # type: ignore[arg-type]
        changes["sensors"] = tuple(sensors)
    return replace(geom, **changes)


def _default_finger(name: str, hand: Hand, hand_length_m: float) -> FingerGeometry:
    ratios = _BUCHHOLZ_RATIOS[name]
    mirror = 1.0 if hand == "right" else -1.0
    if name == "thumb":
        lengths = (ratios[1] * hand_length_m, ratios[3] * hand_length_m)
        px, py, pz = _THUMB_BASE_POSITION_RIGHT_M
        base_pos = (mirror * px, py, pz)
        r = _THUMB_BASE_ROTATION.as_matrix()
        if hand == "left":
            r = MIRROR_X @ r @ MIRROR_X
        base_q = tuple(float(v) for v in matrix_to_quat(r))
        sensor_phalanges = (0, 1)
    else:
        lengths = tuple(r * hand_length_m for r in ratios[1:])
        base_pos = (mirror * _MCP_X_RIGHT_M[name], ratios[0] * hand_length_m, 0.0)
        base_q = (0.0, 0.0, 0.0, 1.0)
        sensor_phalanges = (1, 2)  # the paper's placement (section 2.1)
    sensors = tuple(
        SensorPlacement(f"{name}.{ph}", ph, 0.5 * lengths[ph]) for ph in sensor_phalanges
    )
    return FingerGeometry(name, lengths, base_pos, base_q, 1.0, sensors)  # type: ignore[arg-type]


_SHARED: dict[int, HandCalibration] = {}
"""The shared calibrations by id (each kept alive here, so no other object has its id)."""
_OVERRIDDEN: dict[tuple[int, str], HandCalibration] = {}
"""``with_overrides`` of a shared calibration, by its id and the overrides' exact text."""


def _shared(calib: HandCalibration) -> HandCalibration:
    """``calib`` with its fingers frozen (``FrozenFingers``), noted as shared."""
    out = replace(calib, fingers=FrozenFingers(calib.fingers))
    if len(_SHARED) >= 512:         # (the calibrations dropped here are rebuilt when next asked for)
        _SHARED.clear()
        _OVERRIDDEN.clear()
    _SHARED[id(out)] = out
    return out


def _exact_text(value) -> str | None:
    """The text of a plain value (dicts, lists and tuples of strings, numbers, booleans and ``None``) that
    tells apart any two different values (``repr``: floats to the bit, ``-0.0`` and ``0.0`` too); ``None``
    for anything else, whose ``repr`` may leave out part of its value (e.g. a numpy array's)."""
    stack = [value]
    while stack:
        v = stack.pop()
        kind = type(v)
        if kind is dict:
            stack.extend(v.keys())
            stack.extend(v.values())
        elif kind is list or kind is tuple:
            stack.extend(v)
        elif kind not in (str, float, int, bool, type(None)):
            return None
    return repr(value)


_DEFAULTS: dict[tuple[str, bytes], HandCalibration] = {}
"""The shared default calibrations, by hand and the hand length's bits."""


def default_calibration(hand: Hand = "right", hand_length_m: float = HAND_LENGTH_M) -> HandCalibration:
    """Average adult hand (see module docstring), sensors at mid-phalanx on phalanges 1 and 2 of each
    long finger and on both thumb phalanges: ten IMUs. For a hand length given as a ``float`` (as by
    default), the one shared calibration of that hand and length (``FrozenFingers``)."""
    if hand not in ("right", "left"):
        raise ValueError(f"hand must be 'right' or 'left', got {hand!r}")
    if type(hand_length_m) is not float:
        return HandCalibration(hand, {f: _default_finger(f, hand, hand_length_m) for f in FINGERS})
    key = (hand, struct.pack("d", hand_length_m))
    kept = _DEFAULTS.get(key)
    if kept is None or _SHARED.get(id(kept)) is not kept:
        if len(_DEFAULTS) >= 64:
            _DEFAULTS.clear()
        kept = _DEFAULTS[key] = _shared(HandCalibration(hand, {f: _default_finger(f, hand, hand_length_m)
                                                                 for f in FINGERS}))
    return kept


def calibration_message(calib: HandCalibration) -> dict:
    """The protocol-v1 ``calibration`` message that reproduces ``calib`` exactly."""
    return {
        "type": "calibration",
        "fingers": {
            name: {
                "lengths": list(g.lengths_m),
                "base": {"position": list(g.base_position_m), "orientation": list(g.base_orientation)},
                "coupling": g.coupling,
                "sensors": [
                    {"id": s.id, "phalanx": s.phalanx, "offset": s.offset_m, "mounting": list(s.mounting)}
                    for s in g.sensors
                ],
            }
            for name, g in calib.fingers.items()
        },
    }


def joint_to_phalanx_angles(phi: np.ndarray) -> np.ndarray:
    """Joint angles ``φ`` ``(..., n)`` to phalanx angles ``θ_i = Σ_{j<=i} φ_j`` (paper section 2.1)."""
    return np.cumsum(phi, axis=-1)

