"""Network checks for GigE Vision cameras: socket buffers, each camera's interface (link, MTU,
reverse-path filter) and the packet filter."""
from __future__ import annotations

from rig.doctor.check import FAIL, OK, WARN, Check, mib
from rig.doctor.firewall import Packet, gvsp_verdict
from rig.doctor.host import Host
from rig.doctor.needs import CameraNeeds, RigNeeds
from rig.doctor.routes import covering, interface_for

AREA = "network"
# Receive buffers recommended for GigE Vision streams by camera makers: Balluff's Linux network
# checklist for its GigE cameras sets net.core.rmem_max (and rmem_default) to 16777216
# (assets.balluff.com, "Checklist for Linux", Receive/Transmit Buffers).
VENDOR_RMEM = 16 * 1024 * 1024
# Jumbo frames: Aravis's users are told to set the MTU of the cameras' interfaces to 9000
# (Aravis README and go-aravis's docs: "ip link set <iface> mtu 9000"); Basler's pylon GigE
# configurator sets the largest the NIC takes.
JUMBO_MTU = 9000
# A GVSP data packet carries MTU - 20 (IP) - 8 (UDP) - 8 (GVSP header) bytes of image and costs
# MTU + 38 bytes of line time (14 Ethernet header, 4 FCS, 8 preamble, 12 inter-frame gap).
GVSP_HEADERS, ETHERNET_FRAMING = 36, 38


def _sysctl_fix(key: str, value: int) -> str:
    """Set now and for every boot (one file per key, so running it twice changes nothing)."""
    return (f"sudo sysctl -w {key}={value} && echo '{key} = {value}' | "
            f"sudo tee /etc/sysctl.d/60-rig-{key.replace('.', '-')}.conf >/dev/null")


def _names(cams: list[CameraNeeds]) -> str:
    return ", ".join(c.name for c in cams)


def _rmem_checks(host: Host, gige: list[CameraNeeds]) -> list[Check]:
    out = []
    rmax, rdef = host.sysctl("net.core.rmem_max"), host.sysctl("net.core.rmem_default")
    if not gige:
        for key, v in (("net.core.rmem_max", rmax), ("net.core.rmem_default", rdef)):
            out.append(Check(AREA, key, OK, "n/a" if v is None else str(v), "no GigE camera in the rig"))
        return out
    need = max(c.socket_buffer for c in gige)
    want = max(need, VENDOR_RMEM)
    who = max(gige, key=lambda c: c.socket_buffer).name
    if rmax is None:
        out.append(Check(AREA, "net.core.rmem_max", WARN, "unreadable", f">= {need} ({mib(need)})",
                         note="/proc/sys/net/core/rmem_max cannot be read"))
    elif rmax < need:
        out.append(Check(AREA, "net.core.rmem_max", FAIL, f"{rmax} ({mib(rmax)})", f">= {need} ({mib(need)}, 4 frames of '{who}')",
                         _sysctl_fix("net.core.rmem_max", want),
                         "the kernel caps the stream's receive buffer here: a busy host loses packets"))
    elif rmax < want:
        out.append(Check(AREA, "net.core.rmem_max", WARN, f"{rmax} ({mib(rmax)})", f">= {want} ({mib(want)}, camera makers' advice)",
                         _sysctl_fix("net.core.rmem_max", want)))
    else:
        out.append(Check(AREA, "net.core.rmem_max", OK, f"{rmax} ({mib(rmax)})", f">= {need} ({mib(need)})"))
    # Aravis sizes its socket when the first frame begins; until then packets land in a buffer of
    # rmem_default. A hardware-triggered camera is not primed with a throw-away frame
    # (rig/cameras/aravis.py, _prime_stream), so its first frame must fit.
    frame = max(gige, key=lambda c: c.wire_bytes)
    hw = [c for c in gige if c.hardware and c.wire_bytes > (rdef or 0)]
    need_def = frame.wire_bytes
    if rdef is None:
        out.append(Check(AREA, "net.core.rmem_default", WARN, "unreadable", f">= {need_def} (one frame)"))
    elif rdef >= need_def:
        out.append(Check(AREA, "net.core.rmem_default", OK, f"{rdef} ({mib(rdef)})", f">= {need_def} ({mib(need_def)}, one frame)"))
    else:
        fix = _sysctl_fix("net.core.rmem_default", max(need_def, VENDOR_RMEM))
        if hw:
            out.append(Check(AREA, "net.core.rmem_default", FAIL, f"{rdef} ({mib(rdef)})", f">= {need_def} ({mib(need_def)}, one frame)",
                             fix, f"the first frame of hardware-triggered {_names(hw)} arrives before the stream sizes its buffer"))
        else:
            out.append(Check(AREA, "net.core.rmem_default", WARN, f"{rdef} ({mib(rdef)})", f">= {need_def} ({mib(need_def)}, one frame)",
                             fix, "the first frame of a stream arrives into this buffer (it is thrown away)"))
    return out


def _link_check(host: Host, iface: str, cams: list[CameraNeeds]) -> Check:
    name = f"link {iface} ({_names(cams)})"
    mtu = host.read_int(f"sys/class/net/{iface}/mtu")
    state = host.read(f"sys/class/net/{iface}/operstate")
    speed = host.read_int(f"sys/class/net/{iface}/speed")  # Mb/s; -1 or unreadable on virtual links
    wire = sum(c.wire_rate for c in cams)
    if mtu is None:
        return Check(AREA, name, FAIL, "no such interface", "the interface the route names", note=f"/sys/class/net/{iface} is missing")
    line_bps = wire * (mtu + ETHERNET_FRAMING) / max(mtu - GVSP_HEADERS, 1) * 8
    measured = f"MTU {mtu}, {state or 'state unknown'}, {speed if speed and speed > 0 else '?'} Mb/s"
    needed = f"MTU >= {JUMBO_MTU}, up, >= {line_bps / 1e6:.0f} Mb/s"
    if iface == "lo":
        return Check(AREA, name, OK, measured, "loopback (a camera emulator on this host)")
    if state == "down":
        return Check(AREA, name, FAIL, measured, needed, f"sudo ip link set dev {iface} up",
                     "the interface is down: check the cable and the camera's power")
    if speed and speed > 0 and line_bps > speed * 1e6:
        return Check(AREA, name, FAIL, measured, needed, None if mtu >= JUMBO_MTU else f"sudo ip link set dev {iface} mtu {JUMBO_MTU}",
                     "the link cannot carry these cameras' streams: lower fps or size, or spread them over more ports")
    if mtu < JUMBO_MTU:
        return Check(AREA, name, WARN, measured, needed, f"sudo ip link set dev {iface} mtu {JUMBO_MTU}",
                     "Aravis shrinks the packets to the MTU: about 6 times the packets and interrupts of jumbo frames "
                     "(make it permanent in netplan or NetworkManager)")
    if not speed or speed <= 0:
        return Check(AREA, name, WARN, measured, needed, note="the link speed cannot be read (a virtual link?)")
    return Check(AREA, name, OK, measured, needed)


def _rp_filter_check(host: Host, iface: str, cams: list[CameraNeeds]) -> Check:
    name = f"rp_filter {iface}"
    all_v, if_v = host.sysctl("net.ipv4.conf.all.rp_filter"), host.sysctl(f"net.ipv4.conf.{iface}.rp_filter")
    if all_v is None and if_v is None:
        return Check(AREA, name, WARN, "unreadable", "0 or 2")
    eff = max(all_v or 0, if_v or 0)  # the kernel uses the larger of the two
    measured = f"{eff} (all {all_v}, {iface} {if_v})"
    fix = " && ".join(_sysctl_fix(k, 2) for k in ("net.ipv4.conf.all.rp_filter", f"net.ipv4.conf.{iface}.rp_filter"))
    if eff != 1 or iface == "lo":
        return Check(AREA, name, OK, measured, "0 or 2 (loose)" if iface != "lo" else "any on loopback")
    # Strict mode drops a packet whose source is not routed back out the interface it came in by:
    # two interfaces on the cameras' subnet (a multi-port card) make one of them drop its camera.
    for c in cams:
        routes = covering(host, c.address)
        best = max((p for _, p in routes), default=None)
        ifaces = sorted({i for i, p in routes if p == best})
        if len(ifaces) > 1:
            return Check(AREA, name, FAIL, measured, "0 or 2 (loose)", fix,
                         f"'{c.name}' ({c.address}) is routed by {' and '.join(ifaces)}: strict filtering drops the stream on all but one")
    return Check(AREA, name, WARN, measured, "0 or 2 (loose)", fix,
                 "strict filtering drops a camera's stream whenever its address is not routed back by this interface "
                 "(a camera that fell back to a link-local address, a second port on the same subnet); "
                 "camera makers advise 2 (Balluff's Linux checklist)")


def _firewall_check(host: Host, iface: str, cams: list[CameraNeeds]) -> Check:
    name = f"firewall {iface}"
    needed = "GVSP (UDP from the cameras) accepted"
    if iface == "lo":
        return Check(AREA, name, OK, "loopback", needed)
    dropped = []
    unread = None
    tool = ""
    for c in cams:
        v = gvsp_verdict(host, Packet(iface, c.address))
        tool = v.tool
        if v.allowed is None:
            unread = v.where
        elif not v.allowed:
            dropped.append((c, v.where))
    if dropped:
        c, where = dropped[0]
        addrs = ",".join(sorted({d.address for d, _ in dropped}))
        fix = (f"sudo nft insert rule inet filter input iifname {iface} ip saddr {{ {addrs} }} meta l4proto udp accept"
               if tool == "nft" else f"sudo iptables -I INPUT -i {iface} -s {addrs} -p udp -j ACCEPT")
        return Check(AREA, name, FAIL, f"drops UDP from {', '.join(d.name for d, _ in dropped)} ({where})", needed, fix,
                     "conntrack does not relate the stream to the control channel: it is new traffic "
                     "(ufw: sudo ufw allow in on IFACE from ADDRESS proto udp; the nft rule names the table and chain your filter uses)")
    if unread:
        return Check(AREA, name, WARN, unread, needed, note="run `sudo rig doctor` to read the packet filter")
    return Check(AREA, name, OK, "accepts UDP from " + _names(cams) if tool else "no packet filter tools installed", needed)


def checks(host: Host, needs: RigNeeds) -> list[Check]:
    gige = needs.of("gige")
    out = _rmem_checks(host, gige)
    if not gige:
        out.append(Check(AREA, "camera interfaces", OK, "n/a", "no GigE camera in the rig"))
        return out
    by_iface: dict[str, list[CameraNeeds]] = {}
    for c in gige:
        iface = interface_for(host, c.address)
        if iface is None:
            out.append(Check(AREA, f"route to {c.name} ({c.address})", FAIL, "no route", "an interface on the camera's subnet",
                             note="give the camera's port an address on its subnet (e.g. sudo ip addr add "
                                  "<x.y.z.1/24> dev <iface>), or set the camera's address with arv-tool"))
            continue
        by_iface.setdefault(iface, []).append(c)
    for iface, cams in by_iface.items():
        out.append(_link_check(host, iface, cams))
        out.append(_rp_filter_check(host, iface, cams))
        out.append(_firewall_check(host, iface, cams))
    return out
