"""A hand: aligns optical poses and IMU samples, runs the chosen estimator per finger, emits frames."""
