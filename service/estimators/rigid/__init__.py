"""Orientation cores for one rigid IMU (gyro, accelerometer, optionally a second reference vector
known in the world frame with its sensor-frame counterpart). The finger estimators are built on
them; they also run alone on rigid-body recordings."""
