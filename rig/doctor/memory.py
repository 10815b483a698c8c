"""Memory: room in /dev/shm for the frame rings the rig's camera daemons create (rig/daemon/ring.py)."""
from __future__ import annotations

from rig.daemon import paths
from rig.doctor.check import FAIL, OK, WARN, Check, mib
from rig.doctor.host import Host
from rig.doctor.needs import RigNeeds
from rig.doctor.space import space

AREA = "memory"


def checks(host: Host, needs: RigNeeds) -> list[Check]:
    root = paths.root()
    name = f"shared memory ({root})"
    rings = [c for c in needs.cameras if c.ring_bytes]
    total = needs.ring_bytes
    if not rings:
        return [Check(AREA, name, OK, "n/a", "no camera daemon in the rig")]
    where = host.path(root)
    sp = space(host, where)
    if sp is None:
        return [Check(AREA, name, WARN, "unreadable", f">= {mib(total)}", note=f"cannot read the filesystem of {root}")]
    # rings this rig's daemons already hold are replaced by the new ones: their room counts as free
    held = 0
    rig_dir = host.path(paths.rig_dir(needs.rig))
    for c in rings:
        try:
            held += (rig_dir / paths.ring_path(needs.rig, c.name).name).stat().st_size
        except OSError:
            pass
    free = sp.avail + held
    largest = max(c.ring_bytes for c in rings)
    measured = f"{mib(free)} free of {mib(sp.size)} on {sp.mount}" + (f" (with {mib(held)} of this rig's rings)" if held else "")
    needed = f">= {mib(total)} ({len(rings)} ring{'s' if len(rings) > 1 else ''}, largest {mib(largest)})"
    grow = sp.size + (total + largest - free)
    fix = (f"sudo mount -o remount,size={-(-grow // (1 << 20))}M {sp.mount}" if sp.mount.startswith("/dev/shm")
           else None)
    if free < total:
        return [Check(AREA, name, FAIL, measured, needed, fix,
                      "the daemons cannot create their rings" + ("" if fix else f" ({sp.mount} is not /dev/shm: free room there)")
                      + "; in a container give it more (docker run --shm-size)")]
    # a daemon that restarts creates its new ring before the old one is removed: one more ring's room
    if free < total + largest:
        return [Check(AREA, name, WARN, measured, f"{needed}, + {mib(largest)} for a restart", fix,
                      "a daemon restarting while the others run has no room for its new ring")]
    return [Check(AREA, name, OK, measured, needed)]
