"""Forward kinematics to the 26 joints of OpenXR ``XR_EXT_hand_tracking``, in the world frame.

Joint order and names follow ``XrHandJointEXT`` (palm, wrist, then thumb metacarpal/proximal/distal/
tip, then metacarpal/proximal/intermediate/distal/tip of index, middle, ring and little). Joint
frames are OpenXR's: -Z along the bone toward the fingertip, +Y out of the back of the hand; the
mapping from the finger frame is ``frames.FINGER_TO_OPENXR``. A joint's orientation is that of the
bone that starts at it (the tip takes its distal bone's).

Model simplifications: the metacarpus is rigid, so every metacarpal joint and the palm share its
orientation; the long fingers' metacarpal joints lie on the wrist line (``y = 0``) below their MCP
joints, the thumb's carpometacarpal joint one thumb-metacarpal length (Buchholz ratio 0.251 of hand
length) behind its MCP joint along the thumb's base direction.
"""
from __future__ import annotations

import functools
from typing import Mapping

import numpy as np

from .frames import FINGER_TO_OPENXR, matrix_to_quat, rot_x
from .hand import LONG_FINGERS, HandCalibration, joint_to_phalanx_angles, HAND_LENGTH_M

JOINT_NAMES: tuple[str, ...] = (
    "palm", "wrist",
    "thumb_metacarpal", "thumb_proximal", "thumb_distal", "thumb_tip",
    *(f"{f}_{j}" for f in LONG_FINGERS for j in ("metacarpal", "proximal", "intermediate", "distal", "tip")),
)
assert len(JOINT_NAMES) == 26

THUMB_METACARPAL_M = 0.251 * HAND_LENGTH_M

# Joint radii (OpenXR ``XrHandJointLocationEXT.radius``: distance from the joint centre to the skin),
# taken as half the breadth of the finger across the joint. Breadths are 50th-percentile British
# adults, the mean of men and women, from Pheasant & Haslegrave, "Bodyspace: Anthropometry,
# Ergonomics and the Design of Work", 3rd ed. (2006), table 10.1 (hand dimensions): index finger
# breadth proximal (at the PIP joint) 20 mm, distal (at the DIP joint) 17 mm, thumb breadth (at the
# IP joint) 21.5 mm, hand thickness at the metacarpals 30.5 mm. The table gives the index only: the
# other long fingers scale the index's breadths by their proximal phalanx length relative to the
# index's (from the calibration). MCP joints take the PIP breadth and tips the DIP breadth (no table
# row; the fingertip narrows further, so the tip radius is an upper bound).
_INDEX_PIP_RADIUS_M = 0.5 * 0.020
_INDEX_DIP_RADIUS_M = 0.5 * 0.017
_THUMB_RADIUS_M = 0.5 * 0.0215
_PALM_RADIUS_M = 0.5 * 0.0305


def joint_poses(calib: HandCalibration, joint_angles: dict[str, np.ndarray],
                hand_rotation: np.ndarray, hand_position: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """``name -> (position (3,), orientation [x,y,z,w])`` in the world frame for joint angles
    ``φ`` per finger (rad) and the metacarpus pose (rotation matrix, position). All orientations are
    converted to quaternions in one vectorised call."""
    to_xr = FINGER_TO_OPENXR
    positions: dict[str, np.ndarray] = {}
    rotations: dict[str, np.ndarray] = {}
    hand_xr = hand_rotation @ to_xr

    def world(p_m):
        return hand_position + hand_rotation @ p_m

    middle = calib.finger("middle")
    positions["wrist"], rotations["wrist"] = np.asarray(hand_position, dtype=float).copy(), hand_xr
    positions["palm"], rotations["palm"] = world(0.5 * np.array([0.0, middle.base_position_m[1], 0.0])), hand_xr
    for name, geom in calib.fingers.items():
        theta = joint_to_phalanx_angles(np.asarray(joint_angles[name], dtype=float))
        rb = geom.base_matrix()
        base = np.asarray(geom.base_position_m)
        if name == "thumb":
            meta = base - THUMB_METACARPAL_M * rb[:, 1]
            bones = ("proximal", "distal", "tip")
        else:
            meta = np.array([base[0], 0.0, base[2]])
            bones = ("proximal", "intermediate", "distal", "tip")
        positions[f"{name}_metacarpal"], rotations[f"{name}_metacarpal"] = world(meta), hand_xr
        point = base.copy()
        frames = rb @ rot_x(theta)                                   # (n, 3, 3) phalanx frames
        for i, bone in enumerate(bones):
            r = frames[min(i, len(frames) - 1)]
            positions[f"{name}_{bone}"], rotations[f"{name}_{bone}"] = world(point), hand_rotation @ r @ to_xr
            if i < len(frames):
                point = point + geom.lengths_m[i] * r[:, 1]
    quats = matrix_to_quat(np.stack([rotations[n] for n in JOINT_NAMES]))
    return {n: (positions[n], quats[k]) for k, n in enumerate(JOINT_NAMES)}


_radii: dict[int, tuple[HandCalibration, tuple[float, ...]]] = {}


def joint_radii_list(calib: HandCalibration) -> tuple[float, ...]:
    """``joint_radii`` in ``JOINT_NAMES`` order, kept per calibration object."""
    hit = _radii.get(id(calib))
    if hit is not None and hit[0] is calib:
        return hit[1]
    radii = joint_radii(calib)
    out = tuple(radii[n] for n in JOINT_NAMES)
    if len(_radii) >= 64:
        _radii.clear()
    _radii[id(calib)] = (calib, out)
    return out


def joint_radii(calib: HandCalibration) -> dict[str, float]:
    """``name -> radius`` (m) of each OpenXR joint, from the anthropometric breadths above and the
    calibrated phalanx lengths."""
    radii = {"palm": _PALM_RADIUS_M, "wrist": _PALM_RADIUS_M}
    radii.update({"thumb_metacarpal": _PALM_RADIUS_M, "thumb_proximal": _THUMB_RADIUS_M,
                  "thumb_distal": _THUMB_RADIUS_M, "thumb_tip": _THUMB_RADIUS_M})
    index_proximal_m = calib.finger("index").lengths_m[0]
    for finger in LONG_FINGERS:
        scale = calib.finger(finger).lengths_m[0] / index_proximal_m
        radii[f"{finger}_metacarpal"] = _PALM_RADIUS_M
        for joint, r in (("proximal", _INDEX_PIP_RADIUS_M), ("intermediate", _INDEX_PIP_RADIUS_M),
                         ("distal", _INDEX_DIP_RADIUS_M), ("tip", _INDEX_DIP_RADIUS_M)):
            radii[f"{finger}_{joint}"] = scale * r
    return {n: radii[n] for n in JOINT_NAMES}


@functools.lru_cache(maxsize=256)
def joint_tracked_list(optics_tracking: bool, fingers_measured: tuple[tuple[str, bool], ...]) -> tuple[bool, ...]:
    """``joint_tracked`` in ``JOINT_NAMES`` order for ``fingers_measured`` as ``(finger, measured)`` pairs;
    remembered (a hand has few such combinations, and a frame needs one)."""
    tracked = joint_tracked(optics_tracking, dict(fingers_measured))
    return tuple(tracked[n] for n in JOINT_NAMES)


def joint_tracked(optics_tracking: bool, fingers_measured: Mapping[str, bool]) -> dict[str, bool]:
    """``name -> tracked`` per OpenXR joint: the palm, wrist and metacarpals while the optics track the
    metacarpus; a finger's joints while the optics track and the finger has a live sensor (a finger
    with no live sensor only holds its last or coupled estimate)."""
    tracked = {}
    for name in JOINT_NAMES:
        finger, _, bone = name.partition("_")
        measured = bone == "metacarpal" or fingers_measured.get(finger, True)
        tracked[name] = bool(optics_tracking and measured)
    return tracked


# -- compiled form of ``joint_poses`` ------------------------------------------------------------------------
# ``joint_poses`` above is the reference; ``joint_poses_compiled`` computes the same 26 poses in one numba
# call (``tests/test_openxr_kernel.py``: equal to 1e-12) from the calibration packed once per calibration.

_FINGER_ORDER = ("thumb",) + tuple(LONG_FINGERS)
_PACK = 16          # per finger: n, base rotation (9, row-major), base position (3), lengths (3, zero-padded)
_packed: dict[int, tuple[HandCalibration, np.ndarray]] = {}


def _packed_calibration(calib: HandCalibration) -> np.ndarray:
    """``(6, 16)``: one row per finger in joint order (``_PACK``), then the palm joint's y and the thumb
    metacarpal length; cached per calibration object."""
    hit = _packed.get(id(calib))
    if hit is not None and hit[0] is calib:
        return hit[1]
    out = np.zeros((len(_FINGER_ORDER) + 1, _PACK))
    for f, name in enumerate(_FINGER_ORDER):
        geom = calib.finger(name)
        n = geom.n_phalanges
        out[f, 0] = n
        out[f, 1:10] = geom.base_matrix().ravel()
        out[f, 10:13] = geom.base_position_m
        out[f, 13:13 + n] = geom.lengths_m
    out[-1, 0] = 0.5 * calib.finger("middle").base_position_m[1]
    out[-1, 1] = THUMB_METACARPAL_M
    if len(_packed) >= 64:
        _packed.clear()
    _packed[id(calib)] = (calib, out)
    return out


def joint_poses_compiled(calib: HandCalibration, joint_angles: dict[str, np.ndarray],
                         hand_rotation: np.ndarray, hand_position: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """``joint_poses`` in one compiled call (same arguments, same result to rounding)."""
    positions, quats = joint_pose_arrays(calib, joint_angles, hand_rotation, hand_position)
    return {n: (positions[k], quats[k]) for k, n in enumerate(JOINT_NAMES)}


_kernel: list = [None]
"""``openxr_kernel.joint_poses`` once ``joint_pose_arrays`` has imported it."""


class AnglesLayout:
    """Where each finger's joint angles lie in one array of every finger's (``FingerAngles.flat``): the
    fingers in order (``names``), their angle counts (``counts``), finger ``k``'s angles at ``slices[k]``,
    up to ``ends[k]``; ``padded``, where the kernel's zero-padded (5, 3) angles (``_FINGER_ORDER``) take
    them (``None`` unless the fingers are those five). One object per names and counts
    (``angles_layout``): compared by identity."""

    __slots__ = ("names", "counts", "slices", "slice_of", "ends", "n", "padded")

    def __init__(self, names: tuple[str, ...], counts: tuple[int, ...]):
        self.names, self.counts = names, counts
        self.ends = np.cumsum(counts, dtype=np.int64) if counts else np.zeros(0, dtype=np.int64)
        starts = [0, *self.ends.tolist()[:-1]]
        self.slices = tuple(slice(a, a + c) for a, c in zip(starts, counts))
        self.slice_of = dict(zip(names, self.slices))
        self.n = int(sum(counts))
        self.padded = None
        if sorted(names) == sorted(_FINGER_ORDER) and len(names) == len(_FINGER_ORDER) and max(counts) <= 3:
            row = {f: k for k, f in enumerate(_FINGER_ORDER)}
            self.padded = np.array([3 * row[f] + j for f, c in zip(names, counts) for j in range(c)], dtype=np.int64)


@functools.lru_cache(maxsize=64)
def angles_layout(names: tuple[str, ...], counts: tuple[int, ...]) -> AnglesLayout:
    """The ``AnglesLayout`` of these fingers and angle counts (one object per combination)."""
    return AnglesLayout(names, counts)


class FingerAngles(Mapping):
    """``name -> φ`` (rad) of a frame's fingers over ``flat``, every finger's angles in one float64 array,
    finger after finger as ``layout`` (``AnglesLayout``) says: what reads them all (the joint poses, the
    gesture values, a frame's message) takes the one array, and a finger's angles are a view of it made
    when read (the pipeline's frames are read whole far more often than by finger). Never modified."""

    __slots__ = ("flat", "layout")

    def __init__(self, flat: np.ndarray, layout: AnglesLayout):
        self.flat, self.layout = flat, layout

    def __getitem__(self, name: str) -> np.ndarray:
        return self.flat[self.layout.slice_of[name]]

    def __iter__(self):
        return iter(self.layout.names)

    def __len__(self) -> int:
        return len(self.layout.names)

    def __repr__(self) -> str:
        return f"FingerAngles({dict(self.items())!r})"


def joint_pose_arrays(calib: HandCalibration, joint_angles: dict[str, np.ndarray],
                      hand_rotation: np.ndarray, hand_position: np.ndarray, positions: np.ndarray | None = None,
                      quats: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``joint_poses_compiled`` as two arrays in ``JOINT_NAMES`` order: positions (26, 3) and
    quaternions (26, 4), written into ``positions`` and ``quats`` where given (C-contiguous float64 of those
    shapes)."""
    kernel = _kernel[0]
    if kernel is None:          # imported when first needed (it brings numba), then kept
        from .openxr_kernel import joint_poses as kernel
        _kernel[0] = kernel
    phi = np.zeros((len(_FINGER_ORDER), 3))
    if type(joint_angles) is FingerAngles and joint_angles.layout.padded is not None:
        phi.put(joint_angles.layout.padded, joint_angles.flat)      # one call for the five fingers
    else:
        for f, name in enumerate(_FINGER_ORDER):
            a = joint_angles[name]
            phi[f, :len(a)] = a
    if positions is None:
        positions = np.empty((len(JOINT_NAMES), 3))
    if quats is None:
        quats = np.empty((len(JOINT_NAMES), 4))
    kernel(_packed_calibration(calib), phi, np.ascontiguousarray(hand_rotation, dtype=float),
           np.ascontiguousarray(hand_position, dtype=float), positions, quats)
    return positions, quats
