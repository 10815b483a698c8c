"""Which interface reaches an address: `ip route get` (policy routing included), else the main table
in /proc/net/route by longest prefix; and which interfaces have a route covering it at all."""
from __future__ import annotations

import ipaddress
import re
import socket
import struct
from typing import Optional

from rig.doctor.host import Host


def _proc_routes(host: Host) -> list[tuple[str, ipaddress.IPv4Network, int]]:
    """(interface, network, metric) of each route of /proc/net/route (addresses little-endian hex)."""
    text = host.read("proc/net/route") or ""
    out = []
    for line in text.splitlines()[1:]:
        f = line.split()
        if len(f) < 8:
            continue
        try:
            dest = socket.inet_ntoa(struct.pack("<I", int(f[1], 16)))
            mask = socket.inet_ntoa(struct.pack("<I", int(f[7], 16)))
            flags, metric = int(f[3], 16), int(f[6])
        except (ValueError, struct.error):
            continue
        if not flags & 0x1:  # RTF_UP
            continue
        out.append((f[0], ipaddress.IPv4Network(f"{dest}/{mask}", strict=False), metric))
    return out


def covering(host: Host, address: str) -> list[tuple[str, int]]:
    """(interface, prefix length) of every route in the main table that contains `address`."""
    ip = ipaddress.IPv4Address(address)
    return [(iface, net.prefixlen) for iface, net, _ in _proc_routes(host) if ip in net]


def interface_for(host: Host, address: str) -> Optional[str]:
    """The interface packets to `address` leave by (and the camera's packets come in by)."""
    out = host.run(["ip", "-o", "route", "get", address])
    if out is not None:
        if not out.ok:
            return None  # "Network is unreachable"
        m = re.search(r"\bdev\s+(\S+)", out.stdout)
        if m:
            return m.group(1)
    if ipaddress.IPv4Address(address).is_loopback:
        return "lo"  # the local table, which /proc/net/route does not show
    best = sorted(_proc_routes(host), key=lambda r: (-r[1].prefixlen, r[2]))
    ip = ipaddress.IPv4Address(address)
    return next((iface for iface, net, _ in best if ip in net), None)
