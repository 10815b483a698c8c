"""What an emulated GoPro knows about itself: settings, presets, statuses and the rules that accept
or reject a change. Pure logic behind one lock; the HTTP side (`http_app.py`) and the emulator's
timers call in.

The camera is a HERO12 Black (model 62, Open GoPro 2.0). Ids and option values are those of the
Open GoPro HTTP specification:

- settings 2 (video resolution), 3 (frames per second), 121 (video lens) and 135 (hypersmooth),
  with the options this model offers. Frame rates depend on the resolution (5.3K stops at 60 fps,
  4K at 120 fps), so either setting may refuse an option the other one rules out; video settings
  exist only in the video preset group; nothing changes while encoding; hypersmooth changes only
  while the webcam is off (as the specification's webcam section says).
- A refused change answers 403 with the specification's body: `error` 1 (setting not available
  now), 2 (no such setting), 3 (option not available now) or 4 (no such option), `setting_id`,
  `option_id` and `supported_options` (the options available now, id and display name).
- presets in three groups (video 1000, photo 1001, time lapse 1002); each keeps its own video
  settings, as a camera's presets do, and loading one makes its settings current.
- statuses by id: 1/2/70 battery, 8 busy, 10 encoding, 13 video encoding duration, 32 preview
  stream (the webcam streaming), 38/39 photo and video counts, 82 ready, 93-98 presets, 114 camera
  control, 115/116 USB connected / controlled, and storage figures.
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from typing import Callable, Optional

MODEL_NAME = "HERO12 Black"
MODEL_NUMBER = "62"
FIRMWARE_VERSION = "H23.01.02.32.00"
API_VERSION = "2.0"

SETTING_RESOLUTION, SETTING_FPS, SETTING_LENS, SETTING_HYPERSMOOTH = 2, 3, 121, 135

# option id -> (display name, width, height)
RESOLUTIONS: dict[int, tuple[str, int, int]] = {
    1: ("4K", 3840, 2160), 4: ("2.7K", 2704, 1520), 9: ("1080", 1920, 1080), 100: ("5.3K", 5312, 2988)}
# option id -> frames per second
FRAME_RATES: dict[int, float] = {
    0: 240.0, 1: 120.0, 2: 100.0, 5: 60.0, 6: 50.0, 8: 30.0, 9: 25.0, 10: 24.0, 13: 200.0}
FRAME_RATES_AT: dict[int, frozenset[int]] = {  # resolution option -> the frame-rate options it allows
    1: frozenset({1, 2, 5, 6, 8, 9, 10}),
    4: frozenset({0, 1, 2, 5, 6, 8, 9, 10, 13}),
    9: frozenset({0, 1, 2, 5, 6, 8, 9, 10, 13}),
    100: frozenset({5, 6, 8, 9, 10}),
}
LENSES: dict[int, str] = {
    0: "Wide", 3: "Superview", 4: "Linear", 7: "Max SuperView", 8: "Linear + Horizon Leveling",
    9: "HyperView", 10: "Linear + Horizon Lock"}
HYPERSMOOTH: dict[int, str] = {0: "Off", 1: "Low", 4: "Auto Boost"}
SETTING_NAMES = {SETTING_RESOLUTION: "Video Resolution", SETTING_FPS: "Frames Per Second",
                 SETTING_LENS: "Video Lens", SETTING_HYPERSMOOTH: "Hypersmooth"}
VIDEO_SETTINGS = (SETTING_RESOLUTION, SETTING_FPS, SETTING_LENS, SETTING_HYPERSMOOTH)

# 403 error codes of the specification
NOT_AVAILABLE, NO_SUCH_SETTING, OPTION_NOT_AVAILABLE, NO_SUCH_OPTION = 1, 2, 3, 4

GROUP_VIDEO, GROUP_PHOTO, GROUP_TIMELAPSE = 1000, 1001, 1002
MODE_VIDEO, MODE_TIME_LAPSE_VIDEO, MODE_PHOTO, MODE_PHOTO_NIGHT, MODE_TIME_WARP = 12, 13, 17, 18, 24
PHOTO_MODES = frozenset({MODE_PHOTO, MODE_PHOTO_NIGHT})

# webcam status / error codes (/gopro/webcam/status)
WEBCAM_OFF, WEBCAM_IDLE, WEBCAM_HIGH_POWER, WEBCAM_LOW_POWER = 0, 1, 2, 3
WEBCAM_OK, WEBCAM_ERR_SHUTTER, WEBCAM_ERR_COM_TIMEOUT, WEBCAM_ERR_INVALID_PARAM = 0, 4, 5, 6
WEBCAM_RESOLUTIONS = {7: (1280, 720), 12: (1920, 1080)}  # res parameter -> size (HERO12 Black)
WEBCAM_FOVS = {0: "Wide", 2: "Narrow", 3: "Superview", 4: "Linear"}


@dataclass
class Preset:
    id: int
    group: int
    mode: int
    title_id: int
    icon: int
    settings: dict[int, int] = field(default_factory=dict)  # video presets: setting id -> option
    modified: bool = False

    def to_json(self) -> dict:
        return {"id": self.id, "mode": self.mode, "titleId": self.title_id, "titleNumber": 0, "userDefined": False,
                "icon": self.icon, "isModified": self.modified, "isFixed": True, "customName": "", "isVisible": 1,
                "settingArray": [{"id": k, "value": v, "isCaption": k in (SETTING_RESOLUTION, SETTING_FPS)}
                                 for k, v in self.settings.items()]}


@dataclass
class Refusal:
    """Why a setting change was refused: the specification's 403 body."""

    error: int
    setting_id: int
    option_id: int
    supported: list[tuple[int, str]]

    def to_json(self) -> dict:
        return {"error": self.error, "setting_id": self.setting_id, "option_id": self.option_id,
                "supported_options": [{"id": i, "display_name": n} for i, n in self.supported]}


def nearest_frame_rate_option(fps: float) -> int:
    return min(FRAME_RATES, key=lambda o: (abs(FRAME_RATES[o] - fps), -FRAME_RATES[o]))


def resolution_option_for(width: int, height: int) -> int:
    """The resolution option of a frame size (1080 when none matches)."""
    for option, (_, w, h) in RESOLUTIONS.items():
        if (w, h) == (width, height):
            return option
    return 9


def _presets(resolution: int, fps_option: int) -> list[Preset]:
    if fps_option not in FRAME_RATES_AT[resolution]:
        fps_option = 8
    video = lambda res, fps, lens: {SETTING_RESOLUTION: res, SETTING_FPS: fps, SETTING_LENS: lens,  # noqa: E731
                                    SETTING_HYPERSMOOTH: 4}
    return [
        Preset(0, GROUP_VIDEO, MODE_VIDEO, title_id=1, icon=0, settings=video(resolution, fps_option, 0)),  # Standard
        Preset(1, GROUP_VIDEO, MODE_VIDEO, title_id=0, icon=1, settings=video(4, 5, 3)),  # Activity
        Preset(2, GROUP_VIDEO, MODE_VIDEO, title_id=2, icon=2, settings=video(1, 8, 4)),  # Cinematic
        Preset(65536, GROUP_PHOTO, MODE_PHOTO, title_id=3, icon=3),  # Photo
        Preset(65537, GROUP_PHOTO, MODE_PHOTO_NIGHT, title_id=6, icon=6),  # Night
        Preset(131072, GROUP_TIMELAPSE, MODE_TIME_WARP, title_id=7, icon=7),  # TimeWarp
        Preset(131073, GROUP_TIMELAPSE, MODE_TIME_LAPSE_VIDEO, title_id=8, icon=8),  # Time Lapse
    ]


class CameraState:
    """Settings, presets and statuses of one emulated camera. Every method takes the lock."""

    GROUP_ICONS = {GROUP_VIDEO: 0, GROUP_PHOTO: 1, GROUP_TIMELAPSE: 2}
    GROUP_MODES = {GROUP_VIDEO: [MODE_VIDEO], GROUP_PHOTO: [MODE_PHOTO, MODE_PHOTO_NIGHT],
                   GROUP_TIMELAPSE: [MODE_TIME_WARP, MODE_TIME_LAPSE_VIDEO]}

    def __init__(self, width: int, height: int, fps: float, clock: Callable[[], float] = time.monotonic):
        self.lock = threading.RLock()
        self._clock = clock
        self.presets = {p.id: p for p in _presets(resolution_option_for(width, height), nearest_frame_rate_option(fps))}
        self.current = self.presets[0]
        self.last_in_group = {GROUP_VIDEO: 0, GROUP_PHOTO: 65536, GROUP_TIMELAPSE: 131072}
        self.video_preset = self.presets[0]  # the settings in the state are those of the last video preset
        self.encoding_since: Optional[float] = None
        self.busy_until = 0.0
        self.busy_holds = 0  # work in progress (writing a file) keeps the camera busy
        self.wired_control = False
        self.camera_control = 0
        self.webcam_status = WEBCAM_OFF
        self.webcam_error = WEBCAM_OK
        self.photos = 0
        self.videos = 0

    # --- flags ------------------------------------------------------------------------------------
    @property
    def busy(self) -> bool:
        with self.lock:
            return self.busy_holds > 0 or self._clock() < self.busy_until

    @property
    def encoding(self) -> bool:
        with self.lock:
            return self.encoding_since is not None

    def busy_for(self, seconds: float) -> None:
        with self.lock:
            self.busy_until = max(self.busy_until, self._clock() + seconds)

    @property
    def streaming(self) -> bool:
        with self.lock:
            return self.webcam_status in (WEBCAM_HIGH_POWER, WEBCAM_LOW_POWER)

    @property
    def frame_rate(self) -> float:
        """Frames per second of a video recorded now."""
        with self.lock:
            return FRAME_RATES[self.video_preset.settings[SETTING_FPS]]

    @property
    def in_photo_mode(self) -> bool:
        with self.lock:
            return self.current.mode in PHOTO_MODES

    # --- settings ---------------------------------------------------------------------------------
    def setting(self, setting_id: int) -> Optional[int]:
        with self.lock:
            return self.video_preset.settings.get(setting_id)

    def _options(self, setting_id: int) -> dict[int, str]:
        if setting_id == SETTING_RESOLUTION:
            return {o: RESOLUTIONS[o][0] for o in RESOLUTIONS}
        if setting_id == SETTING_FPS:
            return {o: f"{FRAME_RATES[o]:.2f}" for o in FRAME_RATES}
        if setting_id == SETTING_LENS:
            return dict(LENSES)
        return dict(HYPERSMOOTH)

    def _available_now(self, setting_id: int) -> dict[int, str]:
        options = self._options(setting_id)
        settings = self.video_preset.settings
        if setting_id == SETTING_FPS:
            allowed = FRAME_RATES_AT[settings[SETTING_RESOLUTION]]
            return {o: n for o, n in options.items() if o in allowed}
        if setting_id == SETTING_RESOLUTION:
            return {o: n for o, n in options.items() if settings[SETTING_FPS] in FRAME_RATES_AT[o]}
        return options

    def set_setting(self, setting_id: int, option: int) -> Optional[Refusal]:
        """Apply a change, or say why not (None: applied)."""
        with self.lock:
            if setting_id not in VIDEO_SETTINGS:
                return Refusal(NO_SUCH_SETTING, setting_id, option, [])
            options = self._options(setting_id)
            if option not in options:
                return Refusal(NO_SUCH_OPTION, setting_id, option, sorted(self._available_now(setting_id).items()))
            blocked = (self.encoding_since is not None or self.current.group != GROUP_VIDEO
                       or (setting_id == SETTING_HYPERSMOOTH and self.webcam_status != WEBCAM_OFF))
            if blocked:
                return Refusal(NOT_AVAILABLE, setting_id, option, [])
            available = self._available_now(setting_id)
            if option not in available:
                return Refusal(OPTION_NOT_AVAILABLE, setting_id, option, sorted(available.items()))
            if self.current.settings.get(setting_id) != option:
                self.current.settings[setting_id] = option
                self.current.modified = True
            return None

    # --- presets ----------------------------------------------------------------------------------
    def load_preset(self, preset_id: int) -> bool:
        with self.lock:
            preset = self.presets.get(preset_id)
            if preset is None or self.encoding_since is not None:
                return False
            self.current = preset
            self.last_in_group[preset.group] = preset.id
            if preset.group == GROUP_VIDEO:
                self.video_preset = preset
            return True

    def load_group(self, group: int) -> bool:
        with self.lock:
            if group not in self.last_in_group:
                return False
            return self.load_preset(self.last_in_group[group])

    def presets_json(self) -> dict:
        with self.lock:
            groups = []
            for group in (GROUP_VIDEO, GROUP_PHOTO, GROUP_TIMELAPSE):
                groups.append({"id": group, "icon": self.GROUP_ICONS[group], "canAddPreset": False,
                               "modeArray": self.GROUP_MODES[group],
                               "presetArray": [p.to_json() for p in self.presets.values() if p.group == group]})
            return {"presetGroupArray": groups, "customIconIds": [{"start": 0, "length": 0}],
                    "customTitleIds": [{"start": 18, "length": 0}]}

    # --- the state document -----------------------------------------------------------------------
    def state_json(self, storage_free_kb: int) -> dict:
        with self.lock:
            now = self._clock()
            busy = self.busy
            encoding = self.encoding_since is not None
            status = {
                1: 1, 2: 3, 6: 0, 8: int(busy), 9: 0, 10: int(encoding), 11: 0,
                13: int(now - self.encoding_since) if encoding else 0,
                17: 0, 32: int(self.streaming), 33: 0, 34: storage_free_kb // 4000, 35: storage_free_kb // 7500,
                38: self.photos, 39: self.videos, 54: storage_free_kb, 55: int(not encoding), 60: 100, 70: 78,
                82: int(not (busy or encoding)), 85: 0,
                93: self.last_in_group[GROUP_VIDEO], 94: self.last_in_group[GROUP_PHOTO],
                95: self.last_in_group[GROUP_TIMELAPSE], 96: self.current.group, 97: self.current.id,
                98: int(self.current.modified), 114: self.camera_control, 115: 1, 116: int(self.wired_control),
            }
            settings = dict(self.video_preset.settings)
            return {"status": {str(k): v for k, v in status.items()},
                    "settings": {str(k): v for k, v in settings.items()}}
