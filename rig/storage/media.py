"""A take's videos from cameras that recorded to their own card: `media/CAM/NAME` and `media.json`.

    SEQ/media.json               the manifest: per card camera, the shutter's press and release
                                 and every file it recorded during the take, pending or done
    SEQ/media/CAM/GH010002.MP4   a downloaded video, named as on the camera's card
    SEQ/media/CAM/GH010002.MP4.part   a download under way or cut short (resumed by `rig record fetch`)

The manifest is rewritten (atomically) at every step: before the shutter is pressed (with the card's
files then, so that what the take added can be told later), after the press, after the release, once
the take's files are known (each `pending`), and after each finished download (`done`). Whatever
stops the work, it says what is left to do. docs/sequence-format.md documents it for users.
"""
from __future__ import annotations

import datetime as _dt
import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Optional

from common.files import atomic_write_json
from rig.storage.layout import SequenceError

MANIFEST = "media.json"
MEDIA = "media"
MANIFEST_VERSION = 1
PENDING, DONE = "pending", "done"


def utc_now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds")


@dataclass
class MediaFile:
    camera_path: str  # where it is on the card: 100GOPRO/GH010002.MP4
    file: str  # where it goes in the take: media/CAM/GH010002.MP4
    size: Optional[int]  # bytes, as the camera's media list says
    state: str = PENDING  # pending | done
    seconds: Optional[float] = None  # how long its download took (the last attempt)

    @property
    def directory(self) -> str:
        return self.camera_path.rpartition("/")[0]

    @property
    def name(self) -> str:
        return self.camera_path.rpartition("/")[2]


@dataclass
class CardCamera:
    camera: str
    uri: str
    serial: str
    card_before: list[str] = field(default_factory=list)  # the card's files before the press
    pressed_host_ns: Optional[int] = None  # host monotonic ns (the clock of index.jsonl and flashes.jsonl)
    encoding_host_ns: Optional[int] = None  # when the camera first said it encodes
    released_host_ns: Optional[int] = None
    pressed_utc: Optional[str] = None
    released_utc: Optional[str] = None
    files: Optional[list[MediaFile]] = None  # None: not yet known (the take ended before the card was listed)
    problem: Optional[str] = None  # the last thing that went wrong with this camera

    @property
    def complete(self) -> bool:
        return self.files is not None and all(f.state == DONE for f in self.files)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["state"] = "done" if self.complete else "pending"
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "CardCamera":
        d = dict(d)
        d.pop("state", None)
        files = d.pop("files", None)
        cam = cls(**d)
        cam.files = None if files is None else [MediaFile(**f) for f in files]
        return cam


@dataclass
class MediaManifest:
    root: Path
    cameras: dict[str, CardCamera] = field(default_factory=dict)

    @property
    def path(self) -> Path:
        return self.root / MANIFEST

    def folder(self, camera: str) -> Path:
        return self.root / MEDIA / camera

    def save(self) -> None:
        atomic_write_json(self.path, {"version": MANIFEST_VERSION,
                                      "cameras": {n: c.to_dict() for n, c in self.cameras.items()}})

    @classmethod
    def load(cls, root: str | Path) -> "MediaManifest":
        """The take's manifest; SequenceError (bad input) when the folder is no take with card cameras."""
        root = Path(root)
        path = root / MANIFEST
        if not path.is_file():
            raise SequenceError(f"{root}: no {MANIFEST}: no camera of this take recorded to its card "
                                "(a GoPro with ?record=card in the rig's config)")
        try:
            d = json.loads(path.read_text())
            if d.get("version") != MANIFEST_VERSION:
                raise SequenceError(f"{path}: unsupported manifest version {d.get('version')!r}")
            cameras = {n: CardCamera.from_dict(c) for n, c in d["cameras"].items()}
        except (ValueError, KeyError, TypeError, AttributeError, UnicodeDecodeError) as exc:
            raise SequenceError(f"{path}: corrupt ({exc})") from None
        return cls(root, cameras)

    def done_files(self) -> list[tuple[str, MediaFile]]:
        """(camera, file) of every downloaded file."""
        return [(n, f) for n, c in self.cameras.items() for f in (c.files or []) if f.state == DONE]


def take_file(camera: str, name: str) -> str:
    """Where a camera's file goes in the take (relative to it)."""
    return f"{MEDIA}/{camera}/{name}"


def media_problems(root: str | Path) -> tuple[list[str], list[str]]:
    """(errors, warnings) of a take's card videos for `rig record validate`: a file the manifest says
    is done must be there at its size (else an error); what is still to download is a warning."""
    root = Path(root)
    if not (root / MANIFEST).is_file():
        return [], []
    try:
        manifest = MediaManifest.load(root)
    except SequenceError as exc:
        return [str(exc)], []
    errors, warnings = [], []
    for name, cam in manifest.cameras.items():
        pending = [f for f in cam.files or [] if f.state != DONE]
        if cam.files is None or pending:
            what = "its videos are not listed yet" if cam.files is None else f"{len(pending)} video(s) not downloaded yet"
            warnings.append(f"{MANIFEST}: {name}: {what} (`rig record fetch {root}`)")
        for f in cam.files or []:
            if f.state != DONE:
                continue
            path = root / f.file
            size = path.stat().st_size if path.is_file() else None
            if size is None:
                errors.append(f"{f.file}: missing ({MANIFEST} says it was downloaded)")
            elif f.size is not None and size != f.size:
                errors.append(f"{f.file}: {size} bytes, {MANIFEST} says {f.size}")
    return errors, warnings
