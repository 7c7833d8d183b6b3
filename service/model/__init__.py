"""Hand and finger kinematics, frames and calibration (DESIGN.md, paper section 2.1)."""
