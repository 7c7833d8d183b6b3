"""The compiled OpenXR joint poses (``model/openxr_kernel.py``) equal the numpy/scipy reference
``openxr.joint_poses`` on random poses of both hands and of a recalibrated hand."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.model.hand import default_calibration
from service.model.openxr import JOINT_NAMES, FingerAngles, angles_layout, joint_pose_arrays, joint_poses, joint_poses_compiled


@pytest.mark.parametrize("hand", ["right", "left"])
def test_compiled_joint_poses_equal_the_reference(hand):
    rng = np.random.default_rng(11)
    calib = default_calibration(hand)
    recalibrated = calib.with_overrides({"thumb": {"lengths": [0.05, 0.03]},
                                         "ring": {"base": {"orientation": [0.1, 0.05, -0.08, 0.99]}}})
    for trial in range(40):
        c = recalibrated if trial % 2 else calib
        angles = {n: rng.uniform(-1.5, 3.0, g.n_phalanges) for n, g in c.fingers.items()}
        if trial == 0:
            angles = {n: np.zeros(g.n_phalanges) for n, g in c.fingers.items()}   # identity joint frames
        rotation = Rotation.random(random_state=rng).as_matrix()
        position = rng.normal(0.0, 1.0, 3)
        reference = joint_poses(c, angles, rotation, position)
        compiled = joint_poses_compiled(c, angles, rotation, position)
        assert list(compiled) == list(JOINT_NAMES)
        for name in JOINT_NAMES:
            np.testing.assert_allclose(compiled[name][0], reference[name][0], rtol=0, atol=1e-12, err_msg=name)
            np.testing.assert_allclose(compiled[name][1], reference[name][1], rtol=0, atol=1e-12, err_msg=name)


def test_joint_poses_from_the_pipelines_one_array_of_angles_equal_those_from_a_dict():
    """``FingerAngles`` (every finger's angles in one array, as the pipeline's frames hold them) give the
    same joint poses to the bit as the same angles given finger by finger, the fingers in any order;
    a finger's angles read from it are its slice of the array."""
    rng = np.random.default_rng(12)
    for hand in ("right", "left"):
        calib = default_calibration(hand)
        for order in (tuple(calib.fingers), tuple(reversed(tuple(calib.fingers)))):
            counts = tuple(calib.finger(f).n_phalanges for f in order)
            layout = angles_layout(order, counts)
            flat = rng.uniform(-1.5, 3.0, sum(counts))
            angles = FingerAngles(flat, layout)
            plain = {f: angles[f].copy() for f in order}
            assert list(angles) == list(order) and len(angles) == len(order)
            assert np.array_equal(np.concatenate([plain[f] for f in order]), flat)
            rotation = Rotation.random(random_state=rng).as_matrix()
            position = rng.normal(0.0, 1.0, 3)
            for a, b in zip(joint_pose_arrays(calib, angles, rotation, position),
                            joint_pose_arrays(calib, plain, rotation, position)):
                assert np.array_equal(a, b)


def test_a_frames_poses_written_into_its_numbers_equal_joint_pose_arrays():
    """``openxr_frame_kernel.frame_poses`` (the poses written after the angles in a frame's one array of
    numbers) equals ``joint_pose_arrays`` to the bit, on random angles, poses and finger orders of both hands
    and a recalibrated one, a NaN angle among them; and writes nothing where the array or the padding does not
    fit."""
    from service.model.openxr import _packed_calibration
    from service.model.openxr_frame_kernel import frame_poses

    rng = np.random.default_rng(13)
    for trial in range(60):
        calib = default_calibration("left" if trial % 3 == 0 else "right")
        if trial % 4 == 1:
            calib = calib.with_overrides({"thumb": {"lengths": [0.05, 0.03]}})
        order = tuple(rng.permutation(tuple(calib.fingers)))
        layout = angles_layout(order, tuple(calib.finger(f).n_phalanges for f in order))
        numbers = np.empty(layout.n + 7 * len(JOINT_NAMES))
        flat = numbers[:layout.n]
        flat[:] = rng.uniform(-1.5, 3.0, layout.n)
        if trial == 7:
            flat[2] = np.nan
        rotation = Rotation.random(random_state=rng).as_matrix()
        position = rng.normal(0.0, 1.0, 3)
        assert frame_poses(_packed_calibration(calib), flat, layout.padded, rotation, position, numbers)
        positions, quats = joint_pose_arrays(calib, FingerAngles(flat.copy(), layout), rotation, position)
        written = numbers[layout.n:]
        assert np.array_equal(written, np.concatenate([positions.ravel(), quats.ravel()]), equal_nan=True)
    calib = default_calibration("right")
    layout = angles_layout(tuple(calib.fingers), tuple(g.n_phalanges for g in calib.fingers.values()))
    packed, flat = _packed_calibration(calib), np.zeros(layout.n)
    for numbers, padded in ((np.full(layout.n + 181, 7.0), layout.padded),      # no room for the poses
                            (np.full(layout.n + 182, 7.0), layout.padded[1:]),  # padding not of the angles
                            (np.full(layout.n + 182, 7.0), np.where(layout.padded == layout.padded[-1], 15,
                                                                    layout.padded))):   # beyond (5, 3)
        assert not frame_poses(packed, flat, padded, np.eye(3), np.zeros(3), numbers)
        assert (numbers == 7.0).all()


def test_the_pipelines_frames_hold_joint_pose_arrays_poses():
    """Every frame of a simulated session (faults, a back-of-hand IMU, hand motion) holds in its numbers
    (``openxr_frame_kernel.frame_poses``, written by ``HandSession._frame``) the poses ``joint_pose_arrays``
    gives for its angles and metacarpus pose, to the bit."""
    from service.pipeline.hand import HandSession
    from service.protocol import parse_message
    from service.sim.session import SimConfig, simulate

    session = HandSession("right")
    frames = []
    for m in simulate(SimConfig(motion="grasp", noise="white", seed=6, metacarpus_imu=True, hand_motion="slow-rotation",
                                t_m_s=1.0)).messages():
        frames.extend(session.handle(parse_message(m)).frames)
    assert len(frames) > 50
    for f in frames:
        assert f.joints.numbers is not None and f.joints.angles is f.joint_angles.flat
        positions, quats = joint_pose_arrays(session.calibration, FingerAngles(f.joint_angles.flat.copy(),
                                             f.joint_angles.layout), f.hand_rotation, f.hand_position)
        assert np.array_equal(f.joints.positions, positions) and np.array_equal(f.joints.quats, quats)
        assert np.array_equal(f.joints.numbers[f.joint_angles.layout.n:], np.concatenate([positions.ravel(), quats.ravel()]))
