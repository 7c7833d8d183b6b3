"""Gesture classification (point, grasp, pinch, open) from hand frames."""
