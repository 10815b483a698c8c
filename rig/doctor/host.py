"""What `rig doctor` knows of the host: files read under a root folder, commands run by one runner.

Every probe goes through a `Host`: `read("proc/sys/net/core/rmem_max")` reads `<root>/proc/...`, and
`run(["ip", "-o", "route", "get", addr])` runs a program found on the runner's PATH. The root is "/"
on a real host; a copy of another host's /proc, /sys, /etc and /dev (or a test's tree) works the same,
and a folder of small scripts on PATH stands in for the host's programs. Nothing here writes to the
host: the doctor only reads and measures.
"""
from __future__ import annotations

import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence


@dataclass
class Output:
    """A finished command: exit status and what it printed."""
    rc: int
    stdout: str
    stderr: str

    @property
    def ok(self) -> bool:
        return self.rc == 0


class Runner:
    """Runs a host program with a time limit. `path` replaces $PATH when given (tests put a folder of
    small scripts there); `python` is the interpreter the GPU probes run (the rig's own, so that they
    see the rig's torch and onnxruntime)."""

    def __init__(self, path: Optional[str] = None, python: str = sys.executable, timeout_s: float = 10.0):
        self.path = path
        self.python = python
        self.timeout_s = timeout_s

    def run(self, argv: Sequence[str], timeout_s: Optional[float] = None) -> Optional[Output]:
        """The command's output, or None when the program is not installed (or hangs past the limit:
        a probe that cannot answer in time is a probe that could not be made)."""
        env = dict(os.environ)
        if self.path is not None:
            env["PATH"] = self.path
        env["LC_ALL"] = "C"  # the probes parse English, C-locale output
        try:
            proc = subprocess.run(list(argv), capture_output=True, text=True, env=env, stdin=subprocess.DEVNULL,
                                  timeout=timeout_s or self.timeout_s)
        except (FileNotFoundError, PermissionError, NotADirectoryError):
            return None
        except subprocess.TimeoutExpired:
            return None
        return Output(proc.returncode, proc.stdout, proc.stderr)


@dataclass
class Identity:
    """Who will run the rig: whose access to the devices is checked."""
    uid: int
    gids: frozenset
    name: str

    @classmethod
    def current(cls) -> "Identity":
        import pwd

        uid = os.geteuid()
        try:
            name = pwd.getpwuid(uid).pw_name
        except KeyError:
            name = str(uid)
        return cls(uid, frozenset(os.getgroups()) | {os.getegid()}, name)


class Host:
    """The host the doctor examines: `root` for files, `runner` for programs, `identity` for access."""

    def __init__(self, root: str | os.PathLike = "/", runner: Optional[Runner] = None, identity: Optional[Identity] = None):
        self.root = Path(root)
        self.runner = runner or Runner()
        self.identity = identity or Identity.current()

    def groups(self) -> dict[str, tuple[int, list[str]]]:
        """/etc/group: name -> (gid, member names)."""
        out = {}
        for line in (self.read("etc/group") or "").splitlines():
            f = line.split(":")
            if len(f) >= 4 and f[2].isdigit():
                out[f[0]] = (int(f[2]), [m for m in f[3].split(",") if m])
        return out

    def group_name(self, gid: int) -> str:
        return next((n for n, (g, _) in self.groups().items() if g == gid), str(gid))

    def can_read_write(self, p: str | os.PathLike) -> bool:
        """Whether the identity may open the file for reading and writing, by its owner, group and mode
        (not os.access, which answers for this process, not for the identity)."""
        st = self.path(p).stat()
        ident = self.identity
        if ident.uid == 0:
            return True
        if st.st_uid == ident.uid:
            bits = st.st_mode >> 6
        elif st.st_gid in ident.gids:
            bits = st.st_mode >> 3
        else:
            bits = st.st_mode
        return bits & 0o6 == 0o6

    def path(self, p: str | os.PathLike) -> Path:
        """A host path ("/proc/..." or "proc/...") under the root."""
        return self.root / str(p).lstrip("/")

    def read(self, p: str | os.PathLike) -> Optional[str]:
        """The file's text, stripped, or None when it is missing or unreadable."""
        try:
            return self.path(p).read_text(errors="replace").strip()
        except OSError:
            return None

    def read_int(self, p: str | os.PathLike) -> Optional[int]:
        text = self.read(p)
        try:
            return int(text.split()[0]) if text else None
        except ValueError:
            return None

    def sysctl(self, key: str) -> Optional[int]:
        """An integer sysctl ("net.core.rmem_max") from /proc/sys."""
        return self.read_int("proc/sys/" + key.replace(".", "/"))

    def run(self, argv: Sequence[str], timeout_s: Optional[float] = None) -> Optional[Output]:
        return self.runner.run(argv, timeout_s)
