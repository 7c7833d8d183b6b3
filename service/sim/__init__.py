"""Simulation: finger motions, hand trajectories, sensor error models and recordings with truth."""
