"""OIBAR simulated rig: synthetic world, camera renderer and dataset generator.

Modules are one idea each: `orbit` (target state from a TLE), `sun` (low-precision almanac),
`frames` (LVLH), `rotations`, `camera`, `trajectory`, `ports` (station layout), `meshes`,
`textures`, `render`, `overlay`, `dataset`. The HIL rig (mechanism physics, sim-MCU runner)
will be added beside them.
"""

__version__ = "0.1.0"
