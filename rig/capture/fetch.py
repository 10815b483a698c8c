"""Bring the videos that card-recording cameras made during a take into the take (`rig record` does it
when the take ends; `rig record fetch TAKE` resumes it).

For each camera of the take's media manifest (rig.storage.media) that still has something to do:
1. connect to it at the address its URI names (the manifest keeps the URI the take was recorded with);
2. a shutter the take never released (the recorder was killed) is released now;
3. the take's files are those on the card that were not there before the shutter was pressed (the
   manifest kept that list), each `pending` with its size from the camera's media list;
4. each pending file is downloaded into `media/CAM/` (rig.cameras.gopro_http: a cut-short download
   leaves `NAME.part`, and the next attempt asks for the rest with an HTTP Range request), checked
   against the listed size, and marked `done`.
The manifest is saved after every step. A camera that cannot be reached, or a download that breaks
off, is that camera's `problem`; the other cameras go on.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

from rig.cameras.gopro import card_client
from rig.cameras.gopro_card import CLOSE_TIMEOUT_S
from rig.cameras.gopro_http import MediaItem
from rig.errors import ConfigError, DeviceError
from rig.storage.layout import SequenceError, SequenceMeta
from rig.storage.media import DONE, CardCamera, MediaFile, MediaManifest, take_file, utc_now
from sync.frames import monotonic_ns


def fetch(root: str | Path, cameras: Optional[Sequence[str]] = None, *, notes: Optional[Callable[[str], None]] = None,
          client_options: Optional[dict[str, Any]] = None) -> dict[str, Any]:
    """Download what is missing; the report: per camera its files (state, size, seconds) and problem."""
    root = Path(root)
    SequenceMeta.load(root)  # a take, or SequenceError
    manifest = MediaManifest.load(root)
    names = list(cameras) if cameras else list(manifest.cameras)
    unknown = [n for n in names if n not in manifest.cameras]
    if unknown:
        raise SequenceError(f"{root}: {', '.join(unknown)} did not record to its card in this take "
                            f"(card cameras: {', '.join(manifest.cameras) or 'none'})")
    say = notes or (lambda text: None)
    for name in names:
        entry = manifest.cameras[name]
        if entry.complete:
            continue
        try:
            _fetch_camera(manifest, entry, say, client_options or {})
            entry.problem = None
        except (DeviceError, ConfigError) as exc:
            entry.problem = str(exc)
        except OSError as exc:
            entry.problem = f"{manifest.folder(name)}: could not write the download ({exc.strerror or exc})"
        manifest.save()
    return report(manifest)


def report(manifest: MediaManifest) -> dict[str, Any]:
    return {"path": str(manifest.root), "cameras": {n: c.to_dict() for n, c in manifest.cameras.items()},
            "complete": all(c.complete for c in manifest.cameras.values())}


def _fetch_camera(manifest: MediaManifest, entry: CardCamera, say: Callable[[str], None], options: dict) -> None:
    client = card_client(entry.uri, **options)
    client.connect()
    try:
        if entry.pressed_host_ns is not None and entry.released_host_ns is None and client.state().encoding:
            say(f"{entry.camera}: still recording the take (it ended without releasing the shutter): stopping it")
            entry.released_utc, entry.released_host_ns = utc_now(), monotonic_ns()
            client.shutter_stop()
            client.wait_ready(timeout=CLOSE_TIMEOUT_S)
            manifest.save()
        if entry.files is None:
            client.wait_ready(timeout=CLOSE_TIMEOUT_S)  # a file still being closed is not in the list yet
            before = set(entry.card_before)
            new = [m for m in client.media_list() if m.path not in before]
            if not new:
                entry.files = []
                raise DeviceError(f"{entry.uri}: nothing on the card that was not there before the shutter press "
                                  "(the camera recorded nothing of the take)")
            entry.files = [MediaFile(m.path, take_file(entry.camera, m.name), m.size) for m in new]
            manifest.save()
        for f in entry.files:
            if f.state == DONE:
                continue
            size = f"{f.size / 1e6:.1f} MB" if f.size is not None else "size unknown"
            say(f"{entry.camera}: downloading {f.camera_path} ({size}) into {f.file}")
            t0 = time.monotonic()
            try:
                path = client.download(MediaItem(f.directory, f.name, f.size, None, None), manifest.folder(entry.camera))
            except DeviceError as exc:  # the client's own advice (download again) is what fetch is for
                raise DeviceError(str(exc).removesuffix("; download again to resume")) from None
            f.seconds = round(time.monotonic() - t0, 3)
            f.size = path.stat().st_size
            f.state = DONE
            manifest.save()
    finally:
        client.close()
