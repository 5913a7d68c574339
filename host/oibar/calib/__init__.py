"""Ground-truth calibration toolbox for the motion-capture lab (docs/calibration.md).

Modules, one idea each: transforms (rigid-transform algebra), io (file formats), pnp (pattern
detection and pose), handeye (closed form and motion checks), timing (interpolation and the
time offset), refine (least squares), overlay (visual check), pipeline (estimate / apply),
synthetic (recordings with known truth), cli (`oibar calib ...`).
"""
