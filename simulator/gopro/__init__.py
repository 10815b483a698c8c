"""An emulated GoPro (HERO12 Black, Open GoPro HTTP API 2.0) for tests and demos.

- emulator.py: GoProEmulator - the camera: HTTP on loopback, webcam stream, media, faults.
- http_app.py: the routes of the specification and the HTTP server thread.
- camera_state.py: settings, presets, statuses and what the camera accepts.
- media.py: the SD card (DCIM/100GOPRO), the media list, MP4 / JPEG writers.
- ranges.py: HTTP Range for resumable downloads; faults.py: injected faults.
- advertise.py: the `_gopro-web._tcp.local.` zeroconf advertisement.
- pattern.py: the default picture, with the frame time written into it.
"""
from simulator.gopro.emulator import EmulatorEvent, GoProEmulator, RequestRecord, WebcamInfo, usb_address
from simulator.gopro.media import MediaFile, Recording
from simulator.gopro.pattern import read_time_code, time_code_pattern

__all__ = ["EmulatorEvent", "GoProEmulator", "MediaFile", "Recording", "RequestRecord", "WebcamInfo",
           "read_time_code", "time_code_pattern", "usb_address"]
