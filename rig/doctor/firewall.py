"""Does the host's packet filter let a GigE camera's stream (GVSP) in?

GVSP is UDP from the camera to a port the host chose when it opened the stream. Connection tracking
does not relate it to the control channel (GVCP, UDP 3956, which the host opened), so a filter that
accepts only established/related traffic drops it as new. The question is answered for one packet:
UDP, from the camera's address, in on its interface, to a port not known in advance. Each input base
chain is walked in order: the first rule whose every match this packet meets decides; a rule with a
match the packet may or may not meet (a port, a mark) is passed over, so an accept limited to some
ports is not counted as letting the stream in. nftables (`nft -j list ruleset`, iptables-nft included)
and legacy iptables (`iptables-save`) are read; both need root.
"""
from __future__ import annotations

import ipaddress
import json
import shlex
from dataclasses import dataclass
from typing import Optional

from rig.doctor.host import Host

UNKNOWN = None  # a match the packet may or may not meet


@dataclass
class Packet:
    iface: str
    saddr: str


@dataclass
class Verdict:
    allowed: Optional[bool]  # None: the rules could not be read
    where: str               # the chain (and rule) that decided, or why nothing could be read
    tool: str                # "nft", "iptables", or "" when neither is installed


def _addr_in(addr: str, right) -> Optional[bool]:
    ip = ipaddress.IPv4Address(addr)
    try:
        if isinstance(right, dict) and "prefix" in right:
            p = right["prefix"]
            return ip in ipaddress.IPv4Network(f"{p['addr']}/{p['len']}", strict=False)
        if isinstance(right, dict) and "set" in right:
            return any(_addr_in(addr, r) for r in right["set"])
        if isinstance(right, list):
            return any(_addr_in(addr, r) for r in right)
        if isinstance(right, str):
            return ip in ipaddress.IPv4Network(right, strict=False)
    except (ValueError, KeyError, TypeError):
        return UNKNOWN
    return UNKNOWN


def _values(right) -> list:
    if isinstance(right, dict) and "set" in right:
        return list(right["set"])
    return right if isinstance(right, list) else [right]


def _nft_match(m: dict, pkt: Packet) -> Optional[bool]:
    left, right, op = m.get("left"), m.get("right"), m.get("op", "==")
    if op not in ("==", "!=", "in"):
        return UNKNOWN
    neg = op == "!="
    result: Optional[bool] = UNKNOWN
    if isinstance(left, dict) and "meta" in left:
        key = left["meta"].get("key")
        if key in ("iifname", "iif"):
            result = pkt.iface in _values(right)
        elif key == "l4proto":
            result = "udp" in _values(right) or 17 in _values(right)
        elif key == "nfproto":
            result = "ipv4" in _values(right)
    elif isinstance(left, dict) and "payload" in left:
        p = left["payload"]
        if p.get("protocol") == "ip" and p.get("field") == "saddr":
            result = _addr_in(pkt.saddr, right)
        elif p.get("protocol") == "ip" and p.get("field") == "protocol":
            result = "udp" in _values(right) or 17 in _values(right)
    elif isinstance(left, dict) and "ct" in left and left["ct"].get("key") == "state":
        # GVSP is a new flow for conntrack: neither established nor related
        result = "new" in _values(right) or "untracked" in _values(right)
    if result is UNKNOWN:
        return UNKNOWN
    return (not result) if neg else result


def _nft_verdict(expr: list, pkt: Packet) -> Optional[str]:
    """'accept' / 'drop' when the rule applies to the packet, None when it does not or may not."""
    verdict = None
    for e in expr:
        if "match" in e:
            r = _nft_match(e["match"], pkt)
            if r is not True:
                return None
        elif "accept" in e:
            verdict = "accept"
        elif "drop" in e or "reject" in e:
            verdict = "drop"
        elif "counter" in e or "log" in e or "comment" in e:
            continue
        else:  # jump, goto, set updates, limits...: the packet's fate is not decided here
            return None
    return verdict


def nft_allows(ruleset: dict, pkt: Packet) -> tuple[bool, str]:
    items = ruleset.get("nftables", [])
    chains = [i["chain"] for i in items if "chain" in i and i["chain"].get("hook") == "input"
              and i["chain"].get("family") in ("ip", "inet")]
    rules = [i["rule"] for i in items if "rule" in i]
    for ch in sorted(chains, key=lambda c: c.get("prio", 0)):
        name = f"{ch.get('family')} {ch.get('table')} {ch.get('name')}"
        decided = None
        for rule in rules:
            if (rule.get("family"), rule.get("table"), rule.get("chain")) != (ch.get("family"), ch.get("table"), ch.get("name")):
                continue
            decided = _nft_verdict(rule.get("expr", []), pkt)
            if decided is not None:
                if decided == "drop":
                    return False, f"{name}: rule {rule.get('handle')} drops it"
                break
        if decided is None and ch.get("policy") == "drop":
            return False, f"{name}: policy drop, no rule accepts it"
    return True, "no input chain drops it" if chains else "no input chain"


def _ipt_rule(args: list[str], pkt: Packet) -> Optional[str]:
    verdict, i = None, 0
    while i < len(args):
        a = args[i]
        nxt = args[i + 1] if i + 1 < len(args) else ""
        neg = False
        if a == "!":
            neg, i = True, i + 1
            a = args[i]
            nxt = args[i + 1] if i + 1 < len(args) else ""
        if a in ("-A",):
            i += 2
            continue
        if a in ("-i", "--in-interface"):
            ok = (pkt.iface == nxt) or (nxt.endswith("+") and pkt.iface.startswith(nxt[:-1]))
        elif a in ("-s", "--source"):
            ok = any(_addr_in(pkt.saddr, x) for x in nxt.split(","))
        elif a in ("-p", "--protocol"):
            ok = nxt in ("udp", "17", "all")
        elif a in ("-m", "--match"):
            i += 2
            continue
        elif a in ("--state", "--ctstate"):
            ok = "NEW" in nxt.split(",") or "UNTRACKED" in nxt.split(",")
        elif a in ("-j", "--jump"):
            verdict = {"ACCEPT": "accept", "DROP": "drop", "REJECT": "drop"}.get(nxt)
            if verdict is None:
                return None  # a jump to a user chain, a LOG, ...
            i += 2
            continue
        elif a == "--comment":
            i += 2
            continue
        else:
            return None  # a port, a mark, a limit: may or may not apply
        if ok is None or ok == neg:
            return None
        i += 2
    return verdict


def iptables_allows(save: str, pkt: Packet) -> tuple[bool, str]:
    table, policy = None, None
    for line in save.splitlines():
        line = line.strip()
        if line.startswith("*"):
            table = line[1:]
        elif table == "filter" and line.startswith(":INPUT "):
            policy = line.split()[1]
        elif table == "filter" and line.startswith("-A INPUT "):
            try:
                args = shlex.split(line)
            except ValueError:
                continue
            v = _ipt_rule(args, pkt)
            if v == "drop":
                return False, f"filter INPUT: `{line}` drops it"
            if v == "accept":
                return True, f"filter INPUT: `{line}` accepts it"
    if policy == "DROP":
        return False, "filter INPUT: policy DROP, no rule accepts it"
    return True, "filter INPUT lets it in"


def gvsp_verdict(host: Host, pkt: Packet) -> Verdict:
    nft = host.run(["nft", "-j", "list", "ruleset"])
    if nft is not None:
        if nft.ok:
            try:
                allowed, where = nft_allows(json.loads(nft.stdout or "{}"), pkt)
                return Verdict(allowed, where, "nft")
            except (ValueError, AttributeError, TypeError):
                return Verdict(None, "nft printed no JSON ruleset", "nft")
        return Verdict(None, f"nft cannot list the ruleset ({(nft.stderr.strip().splitlines() or ['exit %d' % nft.rc])[-1]}; run as root)", "nft")
    ipt = host.run(["iptables-save", "-t", "filter"])
    if ipt is not None:
        if ipt.ok:
            allowed, where = iptables_allows(ipt.stdout, pkt)
            return Verdict(allowed, where, "iptables")
        return Verdict(None, "iptables-save cannot read the rules (run as root)", "iptables")
    return Verdict(True, "neither nft nor iptables is installed", "")
