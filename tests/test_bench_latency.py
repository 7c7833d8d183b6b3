"""``bench latency``'s matching of a frame to the message that completed its tick (the pipeline's rule:
the reorder window has passed and a pose covers the tick), on hand-made send logs."""
import numpy as np

from service.bench.latency import completing_sends


def test_a_frame_is_completed_by_the_later_of_the_window_and_the_covering_pose():
    window = 0.02
    sends = [(0.000, "imu_batch", 0.000), (0.001, "pose", 0.005), (0.010, "imu_batch", 0.010),
             (0.020, "imu_batch", 0.020), (0.025, "pose", 0.025), (0.030, "imu_batch", 0.030),
             (0.040, "imu_batch", 0.040)]
    frames = np.array([0.000, 0.010, 0.020, 0.030])
    # t=0: the window passes with the sample at 0.02 (index 3), a pose covers it at index 1 -> 3
    # t=0.01: window at 0.03 (index 5), pose 0.025 >= 0.01 (index 4) -> 5
    # t=0.02: window at 0.04 (index 6), pose 0.025 (index 4) -> 6
    # t=0.03: window at 0.05 never reached -> -1
    assert completing_sends(sends, frames, window).tolist() == [3, 5, 6, -1]


def test_a_pose_arriving_after_the_window_completes_the_frame():
    sends = [(0.0, "imu_batch", 0.00), (0.1, "pose", 0.00), (0.2, "imu_batch", 0.03), (0.3, "imu_batch", 0.05),
             (0.4, "pose", 0.04)]
    assert completing_sends(sends, np.array([0.0, 0.03]), 0.02).tolist() == [2, 4]


def test_the_subscriber_s_collections_are_recorded_with_their_generation():
    import gc

    from service.bench.latency import _gc_pauses

    pauses: list = []
    callback = _gc_pauses(pauses)
    gc.callbacks.append(callback)
    try:
        gc.collect(0)
        gc.collect(2)
    finally:
        gc.callbacks.remove(callback)
    assert [g for g, _ in pauses] == [0, 2]
    assert all(d >= 0.0 for _, d in pauses)
