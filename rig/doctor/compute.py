"""Compute: CPUs, the GPU the model's runtimes see, the live view's reachable rate from `rig model
bench` figures, and the time source."""
from __future__ import annotations

import json
import math
import re
import shlex
from pathlib import Path
from typing import Optional

from rig.doctor.check import FAIL, OK, WARN, Check
from rig.doctor.host import Host
from rig.doctor.needs import RigNeeds

AREA = "compute"
GPU_PROVIDERS = ("CUDAExecutionProvider", "TensorrtExecutionProvider")

# Run in the rig's own interpreter: it answers for the torch and onnxruntime the rig will import.
GPU_PROBE = r"""
import json
out = {}
try:
    import torch
    ok = torch.cuda.is_available()
    out["torch"] = {"version": torch.__version__, "cuda": ok,
                    "devices": [torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count())] if ok else []}
except Exception as exc:
    out["torch"] = {"error": f"{type(exc).__name__}: {exc}"}
try:
    import onnxruntime
    out["onnxruntime"] = {"version": onnxruntime.__version__, "providers": onnxruntime.get_available_providers()}
except Exception as exc:
    out["onnxruntime"] = {"error": f"{type(exc).__name__}: {exc}"}
print(json.dumps(out))
"""


def _count_ranges(text: str) -> Optional[int]:
    """CPUs in a kernel CPU list ("0-3,6")."""
    n = 0
    try:
        for part in text.split(","):
            a, dash, b = part.strip().partition("-")
            first = int(a)  # an empty list or a garbled entry is unreadable, not one CPU
            n += (int(b) - first + 1) if dash else 1
    except ValueError:
        return None
    return n if n > 0 else None


def cpu_count(host: Host) -> tuple[Optional[int], str]:
    online = _count_ranges(host.read("sys/devices/system/cpu/online") or "")
    quota = host.read("sys/fs/cgroup/cpu.max")  # cgroup v2: "max 100000" or "<quota> <period>"
    if quota:
        f = quota.split()
        if len(f) == 2 and f[0] != "max":
            try:
                q = math.ceil(int(f[0]) / int(f[1]))
                if online is None or q < online:
                    return q, f"{q} (cgroup quota {f[0]}/{f[1]}; {online} online)"
            except (ValueError, ZeroDivisionError):
                pass
    return online, f"{online}" if online else "unreadable"


def _cpu_check(host: Host, needs: RigNeeds) -> Check:
    n, measured = cpu_count(host)
    # every camera's daemon (or capture thread) and the session with its recorder keep a core busy
    need = len(needs.cameras) + 1
    needed = f">= {need} (a core per camera and one for the session and recorder)"
    if n is None:
        return Check(AREA, "CPUs", WARN, measured, needed)
    if n < 2:
        return Check(AREA, "CPUs", FAIL, measured, needed, None,
                     "on one core the cameras, the session and the recorder take turns: frames wait and sets fall apart")
    if n < need:
        return Check(AREA, "CPUs", WARN, measured, needed, None, "fewer cores than busy processes: expect drops at full rate")
    return Check(AREA, "CPUs", OK, measured, needed)


def driver_gpus(host: Host) -> list[str]:
    """GPUs the NVIDIA driver sees (nvidia-smi, else /proc/driver/nvidia/gpus)."""
    out = host.run(["nvidia-smi", "-L"])
    if out is not None and out.ok:
        return [line.split(" (UUID")[0] for line in out.stdout.splitlines() if line.startswith("GPU ")]
    try:
        return sorted(p.name for p in host.path("proc/driver/nvidia/gpus").iterdir())
    except OSError:
        return []


def runtime_gpus(host: Host) -> dict:
    out = host.run([host.runner.python, "-c", GPU_PROBE], timeout_s=120)
    if out is None or not out.ok:
        return {"error": "the rig's Python did not answer" if out is None else (out.stderr.strip().splitlines() or ["?"])[-1]}
    try:
        return json.loads(out.stdout.strip().splitlines()[-1])
    except (ValueError, IndexError):
        return {"error": "the GPU probe printed no JSON"}


def _gpu_check(host: Host, needs: RigNeeds) -> Check:
    seen = runtime_gpus(host)
    torch = seen.get("torch", {})
    ort = seen.get("onnxruntime", {})
    names = list(torch.get("devices") or [])
    providers = [p for p in (ort.get("providers") or []) if p in GPU_PROVIDERS]
    parts = []
    if "version" in torch:
        parts.append(f"torch {torch['version']}: {', '.join(names) if names else 'no CUDA'}")
    if "version" in ort:
        parts.append(f"onnxruntime {ort['version']}: {', '.join(providers) if providers else 'CPU only'}")
    if "error" in seen:
        parts.append(seen["error"])
    measured = "; ".join(parts) or "neither torch nor onnxruntime imports"
    needed = "a GPU for the live view at the paper's sizes (docs/live.md)"
    if names or providers:
        return Check(AREA, "GPU", OK, measured, needed)
    driver = driver_gpus(host)
    if driver:
        pip = f"{shlex.quote(host.runner.python)} -m pip install onnxruntime-gpu"
        return Check(AREA, "GPU", FAIL, f"driver sees {', '.join(driver)}; {measured}", needed, pip,
                     "the GPU is there but the rig's runtimes cannot use it: a CPU-only onnxruntime or torch "
                     "(or a CUDA torch wheel from pytorch.org)")
    return Check(AREA, "GPU", WARN, measured, needed, None,
                 "no GPU: the live view runs ONNX Runtime on the CPU at the live size (docs/live.md)")


def bench_rate(bench: dict) -> tuple[float, str]:
    """Sets per second the live view reaches by `rig model bench --json` figures: the faster of the
    ONNX Runtime and torch totals (ms per set: stage 1 once, one view)."""
    runs = bench.get("runs") or [bench]
    best = None
    for r in runs:
        for key in ("ort_ms", "torch_ms"):
            total = (r.get(key) or {}).get("total")
            if isinstance(total, (int, float)) and total > 0 and (best is None or total < best[0]):
                size = r.get("preset") or r.get("size")
                best = (float(total), f"{key[:-3]} {total:g} ms per set at {size}")
    if best is None:
        raise ValueError("no ort_ms.total or torch_ms.total")
    return 1000.0 / best[0], best[1]


def _live_check(needs: RigNeeds, bench: Optional[dict], bench_path: Optional[Path]) -> Check:
    target = needs.live_rate_hz
    if target is None:
        return Check(AREA, "live view rate", OK, "n/a", "no left/right pair in the rig (no live view)")
    needed = f">= {target:g} sets/s (the pair's rate)"
    if bench is None:
        return Check(AREA, "live view rate", WARN, "not measured", needed, None,
                     "measure it: rig model bench --json > bench.json, then rig doctor ... --bench bench.json")
    reach, how = bench_rate(bench)
    measured = f"{reach:.1f} sets/s ({how}, {bench_path})"
    if reach < target:
        return Check(AREA, "live view rate", FAIL, measured, needed, None,
                     "the live view shows every set it can and skips the rest: a GPU (--device cuda), or the live size")
    return Check(AREA, "live view rate", OK, measured, needed)


def _processes(host: Host) -> set[str]:
    names = set()
    try:
        for p in host.path("proc").iterdir():
            if p.name.isdigit():
                try:
                    names.add((p / "comm").read_text().strip())
                except OSError:
                    pass
    except OSError:
        pass
    return names


def _clock_check(host: Host) -> Check:
    name = "time source"
    needed = "synchronised (chrony, systemd-timesyncd or PTP)"
    out = host.run(["chronyc", "-n", "tracking"])
    if out is not None and out.ok:
        leap = re.search(r"Leap status\s*:\s*(.+)", out.stdout)
        offset = re.search(r"System time\s*:\s*([\d.]+) seconds (slow|fast)", out.stdout)
        off = f", {float(offset.group(1)) * 1e3:.3f} ms {offset.group(2)}" if offset else ""
        status = leap.group(1).strip() if leap else "unknown"
        if status == "Normal":
            return Check(AREA, name, OK, f"chrony: {status}{off}", needed)
        return Check(AREA, name, FAIL, f"chrony: {status}{off}", needed, "chronyc sources -v",
                     "chrony reaches no time source: give it one it can reach (a local server or the PTP clock)")
    procs = _processes(host)
    if "ptp4l" in procs:
        pmc = host.run(["pmc", "-u", "-b", "0", "GET TIME_STATUS_NP"])
        if pmc is not None and pmc.ok and "gmPresent" in pmc.stdout:
            m = re.search(r"master_offset\s+(-?\d+)", pmc.stdout)
            present = re.search(r"gmPresent\s+(\w+)", pmc.stdout)
            off = f", offset {int(m.group(1))} ns" if m else ""
            if present and present.group(1) == "true":
                return Check(AREA, name, OK, f"PTP: grandmaster present{off}" + ("" if "phc2sys" in procs else " (no phc2sys)"), needed)
            return Check(AREA, name, FAIL, f"PTP: no grandmaster{off}", needed, None, "ptp4l runs but hears no grandmaster")
        return Check(AREA, name, WARN, "ptp4l runs (its state cannot be read: pmc, as root)", needed)
    td = host.run(["timedatectl", "show", "-p", "NTPSynchronized", "--value"])
    if td is not None and td.ok and td.stdout.strip() in ("yes", "no"):
        if td.stdout.strip() == "yes":
            return Check(AREA, name, OK, "timedatectl: NTPSynchronized=yes", needed)
        return Check(AREA, name, FAIL, "timedatectl: NTPSynchronized=no", needed, "sudo timedatectl set-ntp true",
                     "the clock is not synchronised: takes' wall-clock times and hosts' clocks drift apart")
    return Check(AREA, name, WARN, "no chrony, PTP or timedatectl state readable", needed, None,
                 "install and enable a time service (chrony), or check it as root")


def checks(host: Host, needs: RigNeeds, bench: Optional[dict] = None, bench_path: Optional[Path] = None) -> list[Check]:
    return [_cpu_check(host, needs), _gpu_check(host, needs), _live_check(needs, bench, bench_path), _clock_check(host)]
