"""Finding camera daemons on the network: mDNS / DNS-SD (python-zeroconf).

Each daemon advertises one service of type `_rigcam._tcp.local.`, named `<rig>-<camera>` (ASCII,
renamed `<rig>-<camera>-2` ... by zeroconf when another daemon already holds the name), pointing at
its control API (address and port), with TXT properties:

    v=1  rig  camera  role  uri  model  serial  shm  api (port)  pid  token (1/0)

`advertise(info)` registers it (`wait=False`: the ~1.5 s of conflict probing runs on zeroconf's own
event loop and `Advertisement.ready` is set when it is done); `Advertisement.close()` sends the
goodbye packets. `browse()` lists the daemons that answer, returning once no new one has appeared
for a short quiet period (or at its timeout); beside zeroconf's ServiceBrowser it asks once by
"legacy unicast", which every responder answers at once (see `_ask_by_legacy_unicast`). A service
of the type whose TXT record is not ours (or is damaged) is skipped.
"""
from __future__ import annotations

import asyncio
import ipaddress
import random
import re
import socket
import threading
import time
from dataclasses import asdict, dataclass
from typing import Optional

SERVICE_TYPE = "_rigcam._tcp.local."
TXT_VERSION = "1"
QUIET_S = 0.5  # browse() stops once no new service appeared for this long (after a first match)
REGISTER_TIMEOUT_S = 10.0  # probing + announcing take ~2 s; an event loop this late is stuck
_MAX_INSTANCE = 56  # DNS labels hold 63 bytes; room for zeroconf's "-N" on a name conflict


@dataclass
class DaemonInfo:
    rig: str
    camera: str
    role: str
    uri: str
    model: str
    serial: str
    shm: str  # the frame ring's path on the daemon's host
    host: str  # address of the control API
    port: int  # port of the control API
    pid: int = 0
    token_required: bool = False

    @property
    def api_url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host  # an IPv6 literal
        return f"http://{host}:{self.port}"

    def to_dict(self) -> dict:
        return {**asdict(self), "api_url": self.api_url}


# --- advertising --------------------------------------------------------------------------------

def _label(text: str, limit: int) -> str:
    """ASCII letters, digits, '-' and '_'; any other run of characters becomes one '-'."""
    return re.sub(r"[^A-Za-z0-9_]+", "-", text).strip("-")[:limit].strip("-")


def instance_name(rig: str, camera: str) -> str:
    """The service instance name (without the type): `<rig>-<camera>`, made safe."""
    return _label(f"{rig}-{camera}", _MAX_INSTANCE) or "rig-camera"


def _addresses(host: str, interfaces) -> list[str]:
    """The addresses to advertise for an API bound to `host`."""
    if host and host not in ("0.0.0.0", "::"):
        try:
            return [str(ipaddress.ip_address(host))]
        except ValueError:  # a host name: what it resolves to
            return sorted({ai[4][0] for ai in socket.getaddrinfo(host, None, type=socket.SOCK_STREAM)})
    if isinstance(interfaces, (list, tuple)):  # advertised on these addresses only: reachable there
        found = [a for a in interfaces if isinstance(a, str) and _is_ip(a)]
        if found:
            return found
    import ifaddr  # zeroconf's own dependency

    found = []
    for adapter in ifaddr.get_adapters():
        for ip in adapter.ips:
            addr = ip.ip if isinstance(ip.ip, str) else ip.ip[0]  # IPv6: (address, flowinfo, scope)
            parsed = ipaddress.ip_address(addr.split("%")[0])
            if not (parsed.is_loopback or parsed.is_link_local or parsed.is_unspecified):
                found.append(str(parsed))
    return found or ["127.0.0.1"]


def _zeroconf(interfaces):
    """A Zeroconf instance on `interfaces`: addresses, or an InterfaceChoice (default: All)."""
    from zeroconf import InterfaceChoice, Zeroconf

    if interfaces is None:
        interfaces = InterfaceChoice.All
    return Zeroconf(interfaces=interfaces if isinstance(interfaces, InterfaceChoice) else list(interfaces))


def _is_ip(text: str) -> bool:
    try:
        ipaddress.ip_address(text)
        return True
    except ValueError:
        return False


def _properties(info: DaemonInfo) -> dict[str, str]:
    props = {"v": TXT_VERSION, "rig": info.rig, "camera": info.camera, "role": info.role, "uri": info.uri,
             "model": info.model, "serial": info.serial, "shm": info.shm, "api": str(int(info.port)),
             "pid": str(int(info.pid)), "token": "1" if info.token_required else "0"}
    for key, value in props.items():
        if len(key.encode()) + 1 + len(str(value).encode()) > 255:
            raise ValueError(f"mDNS TXT entry {key!r} is too long (a TXT string holds 255 bytes): {value!r}")
    return props


class Advertisement:
    """A registered service; `close()` withdraws it (goodbye packets) and closes zeroconf."""

    def __init__(self, zc, service):
        self._zc, self.service = zc, service
        self.ready = threading.Event()  # set once registration has finished, successfully or not (`error`)
        self.error: Optional[BaseException] = None
        self._future = None
        self._lock = threading.Lock()
        self._closed = False

    @property
    def name(self) -> str:
        """The registered service name (zeroconf may have renamed it on a conflict)."""
        return self.service.name

    def _start(self, allow_name_change: bool = True) -> None:
        zc, service = self._zc, self.service

        async def register():
            announced = await zc.async_register_service(service, allow_name_change=allow_name_change)
            await announced

        def done(fut):
            self.error = RuntimeError("closed before the registration finished") if fut.cancelled() else fut.exception()
            self.ready.set()

        self._future = asyncio.run_coroutine_threadsafe(register(), zc.loop)
        self._future.add_done_callback(done)

    def wait(self, timeout: Optional[float] = None) -> bool:
        """Wait for the registration; raise its error; False if it is still under way."""
        if not self.ready.wait(timeout):
            return False
        if self.error is not None:
            raise self.error
        return True

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
        if self._future is not None and not self._future.done():
            self._future.cancel()  # still probing: nothing to withdraw yet
            self.ready.wait(2.0)
        self._zc.close()  # sends goodbyes for every service it registered, then stops its thread

    def __enter__(self) -> "Advertisement":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def advertise(info: DaemonInfo, *, interfaces=None, wait: bool = True) -> Advertisement:
    """Advertise a daemon on mDNS. `interfaces`: addresses to use (default: every interface).

    wait=True blocks until the name is probed and announced (~2 s) and raises if it could not be;
    wait=False returns at once (the registration runs on zeroconf's event loop thread:
    `Advertisement.ready` / `.wait()` / `.error`).
    """
    from zeroconf import ServiceInfo

    addresses = _addresses(info.host, interfaces)
    # The server name carries the first address: hosts that share a name (two boxes left at the
    # image's default hostname, or network namespaces on one machine) would otherwise publish one
    # server name, and a browser would merge their addresses and reach one host for both.
    host_label = _label(socket.gethostname().split(".")[0], 40) or "rig-host"
    where = _label(addresses[0].replace(".", "-").replace(":", "-"), 22) if addresses else ""
    service = ServiceInfo(
        SERVICE_TYPE, f"{instance_name(info.rig, info.camera)}.{SERVICE_TYPE}", port=int(info.port),
        properties=_properties(info), server=f"{host_label}{'-' + where if where else ''}.local.",
        parsed_addresses=addresses)
    adv = Advertisement(_zeroconf(interfaces), service)
    try:
        adv._start(allow_name_change=True)
        if wait and not adv.wait(REGISTER_TIMEOUT_S):
            raise TimeoutError(f"mDNS registration of {service.name} did not finish in {REGISTER_TIMEOUT_S:g} s")
    except BaseException:
        adv.close()
        raise
    return adv


# --- browsing -----------------------------------------------------------------------------------

def parse_service(service) -> Optional[DaemonInfo]:
    """A resolved zeroconf ServiceInfo as a DaemonInfo; None when its TXT record is not ours."""
    try:
        props = {k.decode("ascii"): (v or b"").decode("utf-8") for k, v in service.properties.items()}
        if props.get("v") != TXT_VERSION or not props.get("rig") or not props.get("camera"):
            return None
        port = int(service.port or props["api"])
        if not 0 < port < 65536:
            return None
        from zeroconf import IPVersion

        addresses = service.parsed_addresses(IPVersion.V4Only) or service.parsed_addresses()
        host = addresses[0] if addresses else (service.server or "").rstrip(".")
        if not host:
            return None
        return DaemonInfo(rig=props["rig"], camera=props["camera"], role=props.get("role", ""), uri=props.get("uri", ""),
                          model=props.get("model", ""), serial=props.get("serial", ""), shm=props.get("shm", ""),
                          host=host, port=port, pid=int(props.get("pid") or 0), token_required=props.get("token") == "1")
    except Exception:  # noqa: BLE001 - anything damaged in someone else's record: not a daemon of ours
        return None


def _ask_by_legacy_unicast(zc, interfaces, stop: threading.Event) -> None:
    """Ask for every daemon once from a port other than 5353 and feed the answers to `zc`.

    A responder answers such a "legacy unicast" query at once, by unicast (RFC 6762 section 6.7),
    even for records it multicast within the last second, which it would otherwise answer only a
    second later (section 6): a browse started shortly after another (`daemon://` cameras opened
    one after another) would see some daemons a second after the others, past its quiet period.
    Best effort: the ServiceBrowser's own multicast queries find them anyway.
    """
    from zeroconf import DNSIncoming, DNSOutgoing, DNSQuestion
    from zeroconf.const import _CLASS_IN, _FLAGS_QR_QUERY, _MDNS_ADDR, _MDNS_PORT, _TYPE_PTR

    if isinstance(interfaces, (list, tuple)):
        addrs = [a for a in interfaces if isinstance(a, str) and _is_ip(a) and ipaddress.ip_address(a).version == 4]
    else:
        import ifaddr

        addrs = sorted({ip.ip for adapter in ifaddr.get_adapters() for ip in adapter.ips if ip.is_IPv4})
    query = DNSOutgoing(_FLAGS_QR_QUERY, multicast=False, id_=random.randint(1, 0xFFFF))  # an id: not deduplicated
    query.add_question(DNSQuestion(SERVICE_TYPE, _TYPE_PTR, _CLASS_IN))
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sock.bind(("", 0))
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 255)
        for addr in addrs:
            try:
                sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(addr))
                for packet in query.packets():
                    sock.sendto(packet, (_MDNS_ADDR, _MDNS_PORT))
            except OSError:
                continue  # an interface that cannot send: the others still ask
        sock.settimeout(0.05)
        while not stop.is_set():
            try:
                data, source = sock.recvfrom(9000)
            except socket.timeout:
                continue
            try:
                msg = DNSIncoming(data, source)
            except Exception:  # noqa: BLE001 - not DNS
                continue
            if source[1] == _MDNS_PORT and msg.valid and msg.is_response():
                zc.loop.call_soon_threadsafe(zc.record_manager.async_updates_from_response, msg)
    except Exception:  # noqa: BLE001 - best effort (no route, a zeroconf without these internals)
        pass
    finally:
        sock.close()


def browse(timeout: float = 3.0, *, interfaces=None, rig: Optional[str] = None) -> list[DaemonInfo]:
    """The daemons answering on mDNS (of rig `rig` when given), sorted by (rig, camera).

    Waits at most `timeout` seconds, and returns earlier once a daemon was found and no new service
    appeared for QUIET_S.
    """
    from zeroconf import DNSQuestionType, ServiceBrowser, ServiceInfo, ServiceStateChange

    start = time.monotonic()
    deadline = start + max(0.0, timeout)
    lock, changed = threading.Lock(), threading.Event()
    pending: set[str] = set()
    last_new = [start]
    found: dict[str, Optional[DaemonInfo]] = {}  # service name -> parsed (None: not ours)

    def on_change(zeroconf, service_type, name, state_change):
        with lock:
            if state_change is ServiceStateChange.Removed:
                pending.discard(name)
                found.pop(name, None)
            else:  # Added / Updated: (re)read it
                if name not in found and name not in pending:
                    last_new[0] = time.monotonic()
                pending.add(name)
        changed.set()

    zc = _zeroconf(interfaces)
    try:
        browser = ServiceBrowser(zc, SERVICE_TYPE, handlers=[on_change], question_type=DNSQuestionType.QM)
        stop = threading.Event()
        asker = threading.Thread(target=_ask_by_legacy_unicast, args=(zc, interfaces, stop), name="rig-mdns-ask", daemon=True)
        asker.start()
        try:
            while True:
                with lock:
                    todo = sorted(pending)
                for name in todo:
                    wait_ms = int(max(0.0, min(1.0, deadline - time.monotonic())) * 1000)
                    service = ServiceInfo(SERVICE_TYPE, name)
                    if not service.request(zc, wait_ms):
                        if time.monotonic() < deadline:
                            continue  # not answered yet: tried again on the next round
                    parsed = parse_service(service) if service.port else None
                    with lock:
                        if name in pending:
                            pending.discard(name)
                            found[name] = parsed
                now = time.monotonic()
                with lock:
                    matches = any(d is not None and (rig is None or d.rig == rig) for d in found.values())
                    quiet = not pending and now - last_new[0] >= QUIET_S
                if now >= deadline or (matches and quiet):
                    break
                changed.clear()
                changed.wait(min(0.05, max(0.0, deadline - now)))
        finally:
            stop.set()
            asker.join(1.0)
            browser.cancel()
    finally:
        zc.close()
    daemons = [d for d in found.values() if d is not None and (rig is None or d.rig == rig)]
    return sorted(daemons, key=lambda d: (d.rig, d.camera, d.host, d.port))
