"""Two hosts on one machine: network namespaces `hostA` and `hostB` joined by a veth pair, each with
its own addresses, routes, loopback and multicast (so mDNS runs between them as on a LAN).

    with TwoHosts() as hosts:
        proc = hosts.popen("A", [sys.executable, "-m", "rig", "daemon", ...])
        hosts.run("B", [...])
        hosts.link(False); ...; hosts.link(True)     # the cable pulled and plugged back

The addresses are in 198.18.0.0/15, the range set aside for network tests (RFC 2544): nothing is
routed off the machine, no traffic leaves the namespaces. Everything is removed on leaving, also
after a failure (processes started here are killed first). Needs root and `ip netns`: `available()`
says why not where it cannot run.
"""
from __future__ import annotations

import os
import shutil
import signal
import subprocess
from typing import Optional

SUBNET = "198.18.{k}.{host}"
PREFIX = 24


def available() -> Optional[str]:
    """None when namespaces can be made here; else why not (a skip reason)."""
    if shutil.which("ip") is None:
        return "no `ip` command (iproute2)"
    if os.geteuid() != 0:
        return "network namespaces need root"
    probe = f"rigprobe{os.getpid()}"
    r = subprocess.run(["ip", "netns", "add", probe], capture_output=True, text=True)
    if r.returncode != 0:
        return f"`ip netns add` is not allowed here ({r.stderr.strip()})"
    subprocess.run(["ip", "netns", "del", probe], capture_output=True)
    return None


class TwoHosts:
    def __init__(self, tag: Optional[str] = None, clock_offset_s: Optional[dict] = None):
        """`clock_offset_s`: host -> seconds its monotonic clock runs ahead (a time namespace: two
        machines' monotonic clocks count from their own boots)."""
        tag = tag or str(os.getpid() % 100000)
        self.clock_offset_s = dict(clock_offset_s or {})
        self.k = int(tag) % 250 + 1
        self.ns = {"A": f"hostA-{tag}", "B": f"hostB-{tag}"}
        self.dev = {"A": f"vA{tag}"[:15], "B": f"vB{tag}"[:15]}
        self.addr = {"A": SUBNET.format(k=self.k, host=1), "B": SUBNET.format(k=self.k, host=2)}
        self._procs: list[subprocess.Popen] = []

    # --- setting up and tearing down --------------------------------------------------------------
    def _ip(self, *args: str) -> None:
        r = subprocess.run(["ip", *args], capture_output=True, text=True)
        if r.returncode != 0:
            raise RuntimeError(f"ip {' '.join(args)}: {r.stderr.strip()}")

    def __enter__(self) -> "TwoHosts":
        try:
            for h in ("A", "B"):
                self._ip("netns", "add", self.ns[h])
                # IPv4 only: a peer picking the link's IPv6 link-local address (gloo does) cannot reach it without a scope
                for key in ("all", "default"):
                    subprocess.run(["ip", "netns", "exec", self.ns[h], "sysctl", "-qw", f"net.ipv6.conf.{key}.disable_ipv6=1"],
                                   capture_output=True)
            self._ip("link", "add", self.dev["A"], "type", "veth", "peer", "name", self.dev["B"])
            for h in ("A", "B"):
                self._ip("link", "set", self.dev[h], "netns", self.ns[h])
                self._ip("-n", self.ns[h], "link", "set", "lo", "up")
                self._ip("-n", self.ns[h], "addr", "add", f"{self.addr[h]}/{PREFIX}", "dev", self.dev[h])
                self._ip("-n", self.ns[h], "link", "set", self.dev[h], "multicast", "on")
                self._ip("-n", self.ns[h], "link", "set", self.dev[h], "up")
                # mDNS (224.0.0.251) goes out on the veth: the namespace's only link
                self._ip("-n", self.ns[h], "route", "add", "224.0.0.0/4", "dev", self.dev[h])
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        for p in self._procs:
            if p.poll() is None:
                try:
                    os.killpg(p.pid, signal.SIGKILL)
                except OSError:
                    p.kill()
                try:
                    p.wait(10)
                except subprocess.TimeoutExpired:
                    pass
        for h in ("A", "B"):  # whatever else runs in the namespaces (torchrun's workers leave its process group)
            pids = subprocess.run(["ip", "netns", "pids", self.ns[h]], capture_output=True, text=True).stdout.split()
            for pid in pids:
                try:
                    os.kill(int(pid), signal.SIGKILL)
                except (OSError, ValueError):
                    pass
        for h in ("A", "B"):
            subprocess.run(["ip", "netns", "del", self.ns[h]], capture_output=True)  # takes its end of the veth along

    # --- using them -------------------------------------------------------------------------------
    def argv(self, host: str, argv: list) -> list[str]:
        offset = self.clock_offset_s.get(host)
        clock = ["unshare", "--time", "--fork", "--monotonic", str(offset), "--boottime", str(offset)] if offset else []
        return ["ip", "netns", "exec", self.ns[host], *clock, *map(str, argv)]

    def popen(self, host: str, argv: list, **kw) -> subprocess.Popen:
        """A process on `host` (its own process group: killed with everything it started on leaving)."""
        p = subprocess.Popen(self.argv(host, argv), start_new_session=True, **kw)
        self._procs.append(p)
        return p

    def run(self, host: str, argv: list, timeout: float = 120, **kw) -> subprocess.CompletedProcess:
        return subprocess.run(self.argv(host, argv), capture_output=True, text=True, timeout=timeout, **kw)

    def link(self, up: bool) -> None:
        """Take the cable out (False) or plug it back (True): hostA's end of the veth goes down or up."""
        self._ip("-n", self.ns["A"], "link", "set", self.dev["A"], "up" if up else "down")

    def exists(self) -> bool:
        out = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
        return any(ns in out for ns in self.ns.values())
