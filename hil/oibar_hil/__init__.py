"""OIBAR simulated rig: synthetic world, camera renderer, dataset generator and the HIL rig.

Modules are one idea each: `orbit` (target state from a TLE), `sun` (low-precision almanac),
`frames` (LVLH), `rotations`, `camera`, `trajectory`, `ports` (station layout), `relpose`
(camera pose and labels), `meshes`, `textures`, `render`, `overlay`, `dataset`, `bench`
(render throughput). The HIL rig (the real firmware as a simulated MCU in lockstep with the
mechanism's physics and the host's navigation) is the `rig` subpackage.
"""

__version__ = "0.1.0"
