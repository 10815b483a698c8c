"""The emulated camera on mDNS / DNS-SD, as a GoPro on USB announces itself: service type
`_gopro-web._tcp.local.`, instance name = the serial number (the Open GoPro SDK reads the serial
from the instance name and builds the camera's address from its last three digits), pointing at
the HTTP port. No TXT properties: neither the specification nor the SDK names any.

Registration (probing, then announcing: ~1.7 s) runs on zeroconf's own event loop; `start()`
returns at once and `wait()` blocks until it is done.
"""
from __future__ import annotations

import asyncio
import ipaddress
import threading
from typing import Optional

SERVICE_TYPE = "_gopro-web._tcp.local."


def _interfaces(host: str):
    from zeroconf import InterfaceChoice

    try:
        address = ipaddress.ip_address(host)
    except ValueError:
        return InterfaceChoice.All
    return InterfaceChoice.All if address.is_unspecified else [host]


def _addresses(host: str) -> list[str]:
    try:
        address = ipaddress.ip_address(host)
    except ValueError:
        return ["127.0.0.1"]
    if not address.is_unspecified:
        return [host]
    import ifaddr  # zeroconf's own dependency

    found = [ip.ip for adapter in ifaddr.get_adapters() for ip in adapter.ips
             if isinstance(ip.ip, str) and not ipaddress.ip_address(ip.ip).is_link_local]
    return found or ["127.0.0.1"]


class Advertisement:
    """`<serial>._gopro-web._tcp.local.` at host:port until `close()` (goodbye packets)."""

    def __init__(self, serial: str, host: str, port: int):
        from zeroconf import ServiceInfo, Zeroconf

        self.name = f"{serial}.{SERVICE_TYPE}"
        self._zc = Zeroconf(interfaces=_interfaces(host))
        self.service = ServiceInfo(SERVICE_TYPE, self.name, port=int(port), properties={},
                                   server=f"{serial}.local.", parsed_addresses=_addresses(host))
        self.ready = threading.Event()
        self.error: Optional[BaseException] = None
        self._future = None
        self._closed = False

    def start(self) -> "Advertisement":
        zc, service = self._zc, self.service

        async def register():
            announced = await zc.async_register_service(service, allow_name_change=False)
            await announced

        def done(fut):
            self.error = None if fut.cancelled() else fut.exception()
            self.ready.set()

        self._future = asyncio.run_coroutine_threadsafe(register(), zc.loop)
        self._future.add_done_callback(done)
        return self

    def wait(self, timeout: Optional[float] = None) -> bool:
        """True once announced; raises what the registration raised (a serial already advertised)."""
        if not self.ready.wait(timeout):
            return False
        if self.error is not None:
            raise self.error
        return True

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._future is not None and not self._future.done():
            self._future.cancel()
            self.ready.wait(2.0)
        self._zc.close()
