"""One geometry core for flight, training, the simulator and the lab toolbox (numpy only).

- :mod:`oibar.geometry.rotations`: rotation matrices, rotation vectors, quaternions, angles;
- :mod:`oibar.geometry.transforms`: 4x4 rigid transforms and their small-perturbation algebra;
- :mod:`oibar.geometry.camera`: the pinhole camera and the two pixel conventions;
- :mod:`oibar.geometry.docking`: docking frames, the camera mount, misalignment, lateral offset;
- :mod:`oibar.geometry.fixture`: the berthing fixture's dimensions and keypoints;
- :mod:`oibar.geometry.metrics`: the paper's pose-error metrics.

Names carry their units (``_m``, ``_rad``, ``_deg``, ``_px``) and frames (``R_a_b`` maps frame-b
vectors into frame a). This package imports numpy and nothing else: no OpenCV, no torch, no
simulator (tests/host/test_walls.py).
"""
