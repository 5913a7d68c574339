"""OIBAR simulated rig: synthetic world, camera renderer, dataset generator and the HIL rig.

Modules are one idea each: `orbit` (target state from a TLE), `sun` (low-precision almanac),
`frames` (LVLH), `camera` (the renderer's OpenGL projection of oibar.geometry's camera),
`trajectory`, `ports` (station layout), `meshes`, `textures`, `render`, `overlay`, `dataset`
(the generator), `sequence` (reading a written sequence: numpy only). The HIL rig (mechanism
physics, sim-MCU runner) is `oibar_hil.rig`. Rotations, the camera model, the docking frames and
the fixture's numbers come from `oibar.geometry`, shared with flight and training.
"""

# 0.2.0: the port adapters leave the drogue's room free and the throat's latch bore is dark, so
# the throat keypoint is visible where it is (datasets written by 0.1.0 are refused on resume:
# re-render them with --force).
# 0.3.0: the renderer made honest (issue 58): a depth bias of about a texel, so occluders of 1 cm
# shade; the Earth as an extended, occludable light lit where the Sun lights it; exposure and
# gamma settings (datasets written by 0.2.0 are refused on resume: re-render them with --force).
# 0.4.0: Earth-shine in the colour of the ground and clouds under the sunlit disc (the Earth's
# texture, as Mitsuba's environment map lights its path tracer), not a grey albedo of 0.30: 0.13
# to 0.71 of the Sun's irradiance on a nadir-facing plate over three places, against 0.26 grey.
__version__ = "0.4.0"
