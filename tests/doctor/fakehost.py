"""A fake host for the doctor's checks: a root folder with the /proc, /sys, /etc and /dev files a
test writes, and a folder of small shell scripts as the only programs on PATH."""
from __future__ import annotations

import json
from pathlib import Path

from rig.config import parse_config
from rig.doctor.host import Host, Identity, Runner
from rig.doctor.needs import rig_needs


class FakeHost:
    def __init__(self, base: Path):
        self.root = base / "root"
        self.bin = base / "bin"
        self.root.mkdir()
        self.bin.mkdir()
        self.identity = Identity(0, frozenset({0}), "root")

    def file(self, path: str, text: str = "", mode: int | None = None) -> Path:
        p = self.root / path.lstrip("/")
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
        if mode is not None:
            p.chmod(mode)
        return p

    def program(self, name: str, stdout: str = "", rc: int = 0, stderr: str = "") -> None:
        """A program that prints `stdout` (and `stderr`) and exits `rc`, whatever its arguments."""
        q = lambda s: "'" + s.replace("'", "'\\''") + "'"  # noqa: E731
        p = self.bin / name
        p.write_text(f"#!/bin/sh\nprintf '%s' {q(stdout)}\nprintf '%s' {q(stderr)} >&2\nexit {rc}\n")
        p.chmod(0o755)

    def python_probe(self, doc: dict) -> None:
        """The rig's interpreter as the GPU probe sees it: prints what torch and onnxruntime report."""
        self.program("python", json.dumps(doc) + "\n")

    def host(self, **identity) -> Host:
        ident = Identity(**{"uid": self.identity.uid, "gids": self.identity.gids, "name": self.identity.name, **identity})
        return Host(self.root, Runner(path=str(self.bin), python="python"), ident)


def camera(name: str, uri: str, **kw) -> dict:
    return {"name": name, "uri": uri, "width": kw.pop("width", 640), "height": kw.pop("height", 480), **kw}


def needs_of(cameras: list[dict], trigger: dict | None = None, path: str | None = None):
    data = {"rig": {"name": "venue"}, "cameras": cameras}
    if trigger:
        data["trigger"] = trigger
    return rig_needs(parse_config(data, Path(path) if path else None))


def statuses(checks) -> dict[str, str]:
    return {c.name: c.status for c in checks}
