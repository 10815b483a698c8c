"""USB and network checks on a fake host: each check's ok, warn and fail."""
from __future__ import annotations

import json

from rig.doctor import network, usb
from tests.doctor.fakehost import camera, needs_of, statuses

MiB = 1 << 20
U3V = camera("u", "aravis://Basler-acA1920-40uc-22012345")


def u3v_device(fake, name: str, serial: str) -> None:
    d = f"sys/bus/usb/devices/{name}"
    for k, v in {"busnum": "2", "devnum": "5", "idVendor": "2676", "idProduct": "ba02", "serial": serial,
                 "manufacturer": "Basler", "product": "acA1920-40uc"}.items():
        fake.file(f"{d}/{k}", v + "\n")
    for k, v in {"bInterfaceClass": "ef", "bInterfaceSubClass": "05", "bInterfaceProtocol": "00"}.items():
        fake.file(f"{d}:1.0/{k}", v + "\n")


def usbfs(fake, mb: int) -> None:
    fake.file("sys/module/usbcore/parameters/usbfs_memory_mb", f"{mb}\n")


def test_usbfs_ok_without_usb3_vision_cameras_and_with_enough(fake):
    usbfs(fake, 16)
    [c] = usb.checks(fake.host(), needs_of([camera("g", "aravis://192.168.1.20")]))
    assert c.status == "ok" and "no USB3 Vision camera" in c.needed
    u3v_device(fake, "2-1", "22012345")
    usbfs(fake, 1000)
    [c] = usb.checks(fake.host(), needs_of([U3V]))
    assert c.status == "ok" and c.measured == "1000 MB"
    usbfs(fake, 0)  # 0: no limit at all
    assert usb.checks(fake.host(), needs_of([U3V]))[0].status == "ok"


def test_usbfs_warns_below_the_vendors_advice_and_fails_below_the_cameras_need(fake):
    u3v_device(fake, "2-1", "22012345")
    usbfs(fake, 16)  # the kernel's default
    [c] = usb.checks(fake.host(), needs_of([U3V]))
    assert c.status == "warn" and ">= 8 MB" in c.needed  # one camera: Aravis keeps 8 MiB of transfers submitted
    assert "tee /sys/module/usbcore/parameters/usbfs_memory_mb" in c.fix and "1000" in c.fix
    for i, serial in enumerate(("22000001", "22000002", "22000003")):
        u3v_device(fake, f"2-{i + 2}", serial)
    three = [camera(f"u{i}", f"aravis://Basler-{s}") for i, s in enumerate(("22000001", "22000002", "22000003"))]
    [c] = usb.checks(fake.host(), needs_of(three))
    assert c.status == "fail" and ">= 24 MB" in c.needed and c.fix


def test_an_id_named_camera_not_on_the_usb_bus_is_not_counted(fake):
    usbfs(fake, 16)
    [c] = usb.checks(fake.host(), needs_of([camera("x", "aravis://Basler-99999999")]))
    assert c.status == "ok" and "x: GigE, or not plugged in" in c.needed


GIGE = camera("left", "aravis://192.168.1.20", trigger="free")


def sysctls(fake, **values) -> None:
    for key, v in values.items():
        fake.file("proc/sys/" + key.replace("__", "/"), f"{v}\n")


def link(fake, iface="eth1", mtu=9000, state="up", speed=1000, rp=0, rp_all=0) -> None:
    fake.file(f"sys/class/net/{iface}/mtu", f"{mtu}\n")
    fake.file(f"sys/class/net/{iface}/operstate", f"{state}\n")
    fake.file(f"sys/class/net/{iface}/speed", f"{speed}\n")
    sysctls(fake, **{f"net__ipv4__conf__{iface}__rp_filter": rp, "net__ipv4__conf__all__rp_filter": rp_all})


def route_to(fake, iface="eth1") -> None:
    fake.program("ip", f"192.168.1.20 dev {iface} src 192.168.1.1 uid 0 \\    cache \n")


def good_network(fake) -> None:
    sysctls(fake, net__core__rmem_max=16 * MiB, net__core__rmem_default=16 * MiB)
    link(fake)
    route_to(fake)


def by_name(checks, prefix):
    return next(c for c in checks if c.name.startswith(prefix))


def test_network_all_ok(fake):
    good_network(fake)
    fake.program("nft", json.dumps({"nftables": [{"chain": {"family": "inet", "table": "filter", "name": "input",
                                                            "hook": "input", "prio": 0, "policy": "accept"}}]}))
    checks = network.checks(fake.host(), needs_of([GIGE]))
    assert set(statuses(checks).values()) == {"ok"}, [(c.name, c.status, c.measured) for c in checks]
    assert [c.name for c in checks] == ["net.core.rmem_max", "net.core.rmem_default", "link eth1 (left)",
                                        "rp_filter eth1", "firewall eth1"]


def test_no_gige_camera_needs_nothing_of_the_network(fake):
    sysctls(fake, net__core__rmem_max=212992, net__core__rmem_default=212992)
    assert set(statuses(network.checks(fake.host(), needs_of([camera("s", "sim://s")]))).values()) == {"ok"}


def test_rmem_max_warn_and_fail(fake):
    good_network(fake)
    sysctls(fake, net__core__rmem_max=8 * MiB)
    c = by_name(network.checks(fake.host(), needs_of([GIGE])), "net.core.rmem_max")
    assert c.status == "warn" and "sysctl -w net.core.rmem_max=16777216" in c.fix
    sysctls(fake, net__core__rmem_max=212992)
    c = by_name(network.checks(fake.host(), needs_of([GIGE])), "net.core.rmem_max")
    assert c.status == "fail" and ">= 4194304" in c.needed  # Aravis asks max(4 frames, 4 MiB)
    big = camera("big", "aravis://192.168.1.20", width=4096, height=3000, pixel_format="RGB8")
    c = by_name(network.checks(fake.host(), needs_of([big])), "net.core.rmem_max")
    assert c.status == "fail" and f">= {4 * 4096 * 3000 * 3}" in c.needed


def test_rmem_default_fails_only_for_a_hardware_triggered_cameras_first_frame(fake):
    good_network(fake)
    sysctls(fake, net__core__rmem_default=212992)  # smaller than one 640x480 frame (307200 bytes)
    assert by_name(network.checks(fake.host(), needs_of([GIGE])), "net.core.rmem_default").status == "warn"
    hw = [camera("left", "aravis://192.168.1.20", trigger="hardware")]
    c = by_name(network.checks(fake.host(), needs_of(hw, trigger={"uri": "serial:///dev/ttyACM0"})), "net.core.rmem_default")
    assert c.status == "fail" and "left" in c.note


def test_link_mtu_warn_down_fail_and_too_slow_fail(fake):
    good_network(fake)
    link(fake, mtu=1500)
    c = by_name(network.checks(fake.host(), needs_of([GIGE])), "link")
    assert c.status == "warn" and c.fix == "sudo ip link set dev eth1 mtu 9000"
    link(fake, state="down")
    assert by_name(network.checks(fake.host(), needs_of([GIGE])), "link").status == "fail"
    link(fake, speed=100)  # 640x480 Mono8 at 30 fps is ~75 Mb/s of image; at 200 fps it is not 100 Mb/s
    fast = [camera("left", "aravis://192.168.1.20", fps=200.0)]
    c = by_name(network.checks(fake.host(), needs_of(fast)), "link")
    assert c.status == "fail" and "cannot carry" in c.note
    assert by_name(network.checks(fake.host(), needs_of([GIGE])), "link").status == "ok"


def test_no_route_to_a_camera_fails(fake):
    good_network(fake)
    fake.program("ip", "", rc=2, stderr="RTNETLINK answers: Network is unreachable\n")
    checks = network.checks(fake.host(), needs_of([GIGE]))
    assert statuses(checks)["route to left (192.168.1.20)"] == "fail"


def test_route_falls_back_to_proc_net_route_without_ip(fake):
    good_network(fake)
    (fake.bin / "ip").unlink()
    fake.file("proc/net/route", "Iface\tDestination\tGateway\tFlags\tRefCnt\tUse\tMetric\tMask\tMTU\tWindow\tIRTT\n"
                                "eth0\t00000000\t0101A8C0\t0003\t0\t0\t0\t00000000\t0\t0\t0\n"
                                "eth1\t0001A8C0\t00000000\t0001\t0\t0\t0\t00FFFFFF\t0\t0\t0\n")
    assert "link eth1 (left)" in statuses(network.checks(fake.host(), needs_of([GIGE])))


def test_rp_filter_strict_warns_and_fails_with_two_ports_on_the_cameras_subnet(fake):
    good_network(fake)
    link(fake, rp=1)
    fake.file("proc/net/route", "Iface\tDestination\tGateway\tFlags\tRefCnt\tUse\tMetric\tMask\tMTU\tWindow\tIRTT\n"
                                "eth1\t0001A8C0\t00000000\t0001\t0\t0\t0\t00FFFFFF\t0\t0\t0\n")
    c = by_name(network.checks(fake.host(), needs_of([GIGE])), "rp_filter")
    assert c.status == "warn" and "net.ipv4.conf.eth1.rp_filter=2" in c.fix
    fake.file("proc/net/route", "Iface\tDestination\tGateway\tFlags\tRefCnt\tUse\tMetric\tMask\tMTU\tWindow\tIRTT\n"
                                "eth1\t0001A8C0\t00000000\t0001\t0\t0\t0\t00FFFFFF\t0\t0\t0\n"
                                "eth2\t0001A8C0\t00000000\t0001\t0\t0\t0\t00FFFFFF\t0\t0\t0\n")
    c = by_name(network.checks(fake.host(), needs_of([GIGE])), "rp_filter")
    assert c.status == "fail" and "eth1 and eth2" in c.note
    link(fake, rp=0, rp_all=1)  # the kernel takes the larger of all and the interface's
    assert by_name(network.checks(fake.host(), needs_of([GIGE])), "rp_filter").status == "fail"
    link(fake, rp=2, rp_all=1)
    assert by_name(network.checks(fake.host(), needs_of([GIGE])), "rp_filter").status == "ok"


def nft_ruleset(policy: str, rules: list[list[dict]]) -> str:
    items = [{"chain": {"family": "inet", "table": "filter", "name": "input", "handle": 1, "type": "filter",
                        "hook": "input", "prio": 0, "policy": policy}}]
    items += [{"rule": {"family": "inet", "table": "filter", "chain": "input", "handle": i + 2, "expr": e}}
              for i, e in enumerate(rules)]
    return json.dumps({"nftables": items})


ESTABLISHED = [{"match": {"op": "in", "left": {"ct": {"key": "state"}}, "right": ["established", "related"]}}, {"accept": None}]
FROM_IFACE = [{"match": {"op": "==", "left": {"meta": {"key": "iifname"}}, "right": "eth1"}}, {"accept": None}]
SSH_ONLY = [{"match": {"op": "==", "left": {"payload": {"protocol": "tcp", "field": "dport"}}, "right": 22}}, {"accept": None}]


def test_firewall_nft_drop_policy_with_only_established_accepted_fails(fake):
    good_network(fake)
    fake.program("nft", nft_ruleset("drop", [ESTABLISHED, SSH_ONLY]))
    c = by_name(network.checks(fake.host(), needs_of([GIGE])), "firewall")
    assert c.status == "fail" and "policy drop" in c.measured
    assert c.fix.startswith("sudo nft insert rule inet filter input iifname eth1 ip saddr { 192.168.1.20 }")
    fake.program("nft", nft_ruleset("drop", [ESTABLISHED, FROM_IFACE]))
    assert by_name(network.checks(fake.host(), needs_of([GIGE])), "firewall").status == "ok"
    drop_all = [{"match": {"op": "==", "left": {"payload": {"protocol": "ip", "field": "saddr"}},
                           "right": {"prefix": {"addr": "192.168.1.0", "len": 24}}}}, {"drop": None}]
    fake.program("nft", nft_ruleset("accept", [drop_all]))
    assert by_name(network.checks(fake.host(), needs_of([GIGE])), "firewall").status == "fail"


def test_firewall_iptables_and_unreadable_and_absent(fake):
    good_network(fake)
    fake.program("iptables-save", "*filter\n:INPUT DROP [0:0]\n-A INPUT -m conntrack --ctstate RELATED,ESTABLISHED -j ACCEPT\n"
                                  "-A INPUT -p tcp -m tcp --dport 22 -j ACCEPT\nCOMMIT\n")
    c = by_name(network.checks(fake.host(), needs_of([GIGE])), "firewall")
    assert c.status == "fail" and c.fix == "sudo iptables -I INPUT -i eth1 -s 192.168.1.20 -p udp -j ACCEPT"
    fake.program("iptables-save", "*filter\n:INPUT DROP [0:0]\n-A INPUT -i eth1 -p udp -j ACCEPT\nCOMMIT\n")
    assert by_name(network.checks(fake.host(), needs_of([GIGE])), "firewall").status == "ok"
    fake.program("nft", "", rc=1, stderr="Error: Operation not permitted\n")
    c = by_name(network.checks(fake.host(), needs_of([GIGE])), "firewall")
    assert c.status == "warn" and "Operation not permitted" in c.measured
    (fake.bin / "nft").unlink()
    (fake.bin / "iptables-save").unlink()
    c = by_name(network.checks(fake.host(), needs_of([GIGE])), "firewall")
    assert c.status == "ok" and c.measured == "no packet filter tools installed"
