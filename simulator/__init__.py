"""Synthetic scene, renderer with ground truth, virtual sensors and hardware emulators.

- scene.py: Scene(seed, people, motion, board) - room, props, moving people, a calibration board
  carried along a path; pure function of (seed, time).
- render.py: render(scene, camera, t) -> Render (rgb, depth, mask, ids, radiance[, normals]);
  rays.py: each pixel's exactly undistorted ray, cached per camera; shading.py: lights, materials,
  textures and contact shadows.
- rig.py: virtual_rig(n, width, height) - ground-truth calibration of the arc rig.
- sensor.py: SensorModel (exposure, motion blur, gain, noise, colour filter, timing, drops, loop
  replay), SimRig / camera_source for the sim:// camera backend.
- calibration_session.py: CalibrationSession - the rig's scene during `rig calibrate capture`: the
  user's board held at stations planned to cover every camera's image, no people; time counted in views.
- snapshot.py: write_snapshot (behind `rig sim snapshot`).
- options.py: the option tables of the sim config; trigger_board.py: the trigger-board emulator;
  serial_link.py: the emulated board's pty / socket port and its queue of outgoing lines.
"""
