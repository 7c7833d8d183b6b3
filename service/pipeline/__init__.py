"""A hand: aligns optical poses and IMU samples, runs the chosen estimator per finger, emits frames
(``hand``); the tracked hand adds the gesture recogniser (``tracked``)."""
