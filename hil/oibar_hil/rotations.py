"""Rotation helpers: the host package owns them (oibar.rotations), the synthetic world and the
rig use the same functions so both sides agree on every convention."""

from oibar.rotations import (matrix_to_quat, matrix_to_rotvec, quat_to_matrix, rot_x, rot_y, rot_z,  # noqa: F401
                             rotation_angle_deg, rotvec_to_matrix)
