"""The help texts of ``oibar nav`` and ``oibar pose`` (oibar.nav.cli): what each does, the forms
of camera, port and vehicle, and the exit statuses, which docs/navigation.md repeats (the EXIT_*
constants of oibar.nav.cli; tests/host/test_nav_failfast.py checks that both list them all)."""

from __future__ import annotations

NAV_DESCRIPTION = """\
Run the OIBAR navigation daemon: every 100 ms take the newest camera frame, estimate the
relative pose of the berthing fixture with OibarNet (ONNX), filter it, decide the guidance
(phase, velocity setpoint, hold or retreat) and command the docking mechanism's MCU over the
serial link. One status line shows what it is doing; Ctrl-C or SIGTERM stops it cleanly
(vehicle hold, the MCU session ended as planned: valves closed, mechanism held or homed, no
fault raised; link and camera closed, log footer written).

The flight is logged as MCAP (--log; Foxglove, `mcap` and `oibar replay` read it): every
cycle's estimate, filter state with sigmas, guidance command, the MCU's telemetry and events,
the intrinsics and versions; with --record-frames every frame read too, so `oibar replay`
reproduces the estimates exactly. --live serves the same channels to the Foxglove app while it
flies (the camera with the fixture's outline over it, the pose, the link).
"""

NAV_EPILOG = """\
camera (--camera):
  0, 1, ...            an OpenCV camera device index (/dev/video0, ...)
  /dev/video2          a V4L2 device path
  approach.mp4         a video file (played at its frame rate)
  frames/              a folder of images (frames.csv with times if present, else --camera-rate-hz)
  frames+tcp://H:P     RGB frames from another process over a local TCP socket
                       (oibar.camera.stream; `make sitl` feeds the rig's renderer this way)

port (--port):
  /dev/ttyACM0, COM3   the MCU's serial port (115200 baud)
  socket://HOST:PORT   a TCP bridge, e.g. the STM32 image under QEMU
  none                 no MCU: navigation and logging only; guidance holds

vehicle (--vehicle), where velocity setpoints go:
  none                 keep them in the log only (default)
  udp://HOST:PORT      one JSON datagram per cycle for the vehicle's GNC computer;
                       its odometry datagrams back are fused, and each frame's
                       attitude is checked against its relative attitude
                       (oibar.nav.vehicle, oibar.nav.integrity)
  python:MOD:CLASS     your own oibar.nav.vehicle.VehicleInterface subclass

examples:
  oibar nav --camera 0 --port /dev/ttyACM0 --model models/oibarnet.onnx
  oibar nav --camera data/synthetic/seq01/frames --port none --record-frames --duration-s 60
  oibar nav --camera 0 --calibration camera.yaml --port /dev/ttyACM0
  oibar nav --camera 0 --port /dev/ttyACM0 --live            # Foxglove: ws://127.0.0.1:8765
  oibar replay runs/nav/20261122-101500/flight.mcap --model models/other.onnx

calibration (--calibration FILE): the camera that takes the frames, as OpenCV's calibration
YAML (`oibar calibrate-camera`) or ROS camera_info YAML (plumb_bob, rational_polynomial or no
distortion; any resolution). Each frame is undistorted and remapped to the network's canonical
camera (744x480, f 583.33 px) by one cv2.remap; a camera narrower than that view is accepted
with a warning (its uncovered border is black). A frame of another size than the calibration's
is refused (a hold, "malformed frame"), never guessed. Without it, only 744x480 frames of the
canonical camera are read.

exit status (one line on stderr says why; never a traceback):
  0    mission over, --duration-s reached, or Ctrl-C / SIGTERM: the MCU accepted the planned
       end of the session (CMD_END_SESSION), or there is no MCU (--port none)
  1    an unexpected internal error (run with -v for the traceback); the MCU session is
       still ended as planned first
  2    bad argument (on the command line or in the configuration file, --config) or
       start-up error: model, camera spec, empty or undecodable source, vehicle, log folder
  3    the camera source ended (last frame of a video file or frame folder); MCU safe first
  4    the camera source died: no frame for --camera-dead-s (camera unplugged, never
       opened); MCU safe first
  5    stopped otherwise cleanly (0 above), but the MCU did not accept the planned end (link
       down, no answer): it takes the silence for a host link loss (FAULT outside
       BOOT/IDLE/FAULT, valves closed)
  130  Ctrl-C before the daemon was running
A corrupt frame (a truncated JPEG in a folder) is skipped and counted, not an error.
"""


POSE_DESCRIPTION = """\
Estimate the berthing fixture's pose in each image file with OibarNet, without the daemon: one
JSON line per frame on stdout, in the order given:
  {"frame": PATH, "T_cam_target_m": [x, y, z], "q_cam_target_wxyz": [w, x, y, z],
   "confidence": 0..1, "flags": [...], "latency_ms": MS, "crops": N}
("crops": the crop windows the search read through the keypoint networks, what the time went on)
Each frame is read cold, on its own, with the full search (no crop budget, nothing carried from
the previous frame). A frame that cannot be read or is refused gives a line with "error" (the
pose fields null) and one line on stderr.
"""

POSE_EPILOG = """\
frames: the network's canonical camera (744x480, f 583.33 px, principal point at the centre)
unless --calibration names the camera that took them (any resolution: undistorted and remapped
to the canonical camera); a frame whose size does not match the calibration is refused.

examples:
  oibar pose frame.png
  oibar pose shots/*.jpg --calibration camera.yaml > poses.jsonl

exit status (one line on stderr says why; never a traceback):
  0    every frame read and estimated (a low confidence or a flag is an answer, not an error)
  1    an unexpected internal error (run with -v for the traceback)
  2    bad argument (command line or configuration file) or start-up error: model,
       calibration file
  3    at least one frame could not be read (missing, corrupt, not an image) or was refused
       (wrong size, not RGB); the others are still estimated
"""
