"""The GPU path end to end, in one command of under 8 minutes on a bare GPU machine.

    python3 benchmarks/gpu_check.py --carry .gpu-carry --out $OUT        # on the GPU machine
    .venv/bin/python benchmarks/gpu_check.py --device cpu --dry-run --out DIR   # anywhere: tiny sizes, seconds a step
    .venv/bin/python benchmarks/gpu_check.py --prepare .gpu-carry         # here: the wheels to carry there

Steps, each in its own process with its own time limit (one failing or hanging does not stop the
others; the whole keeps to --budget-s):
  1 cuda_tests   the tests marked `cuda` (pytest)
  2 model_speed  stage 1 and the view, eager against torch.compile, fp32 and bf16 autocast, at the
                 paper's and the preview sizes: median ms of N CUDA-synchronised runs after warm-up,
                 and the image's max abs difference from the torch CPU reference (fp32 within 1e-3)
  3 live_engine  rig.live.engine.LiveEngine (no web server) on a replayed simulator take at the
                 paper's sizes with the torch runtime: fps in and out, latency p50/p95
  4 train        `rig train` from the shipped checkpoint for 3 minutes: steps/s, the checkpoint
    eval         `rig model eval` of that checkpoint on a held-out take (another seed)
The two simulator takes are rendered in the background while steps 1 and 2 run.

Results: DIR/gpu_check.json (every step: status passed / failed / skipped, why, seconds, figures)
and a one-line summary, printed last and written to DIR/gpu_check.txt. Exit 0 when no step failed.

The GPU machine has python3 with torch, numpy, OpenCV, onnx and onnxruntime, and nothing can be
fetched there: the project runs from the working tree (PYTHONPATH = the repo root, `python3 -m
rig`), and what else the steps import (pytest for step 1, matplotlib for rig train's loss curve) is
carried as wheels made here with --prepare, unpacked there (standard library only) for the packages
the machine lacks. This script itself imports only the standard library; its steps import the
project.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import re
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
RESULTS = "gpu_check.json"
SUMMARY = "gpu_check.txt"
STEPS = ("cuda_tests", "model_speed", "live_engine", "train", "eval")
# Seconds each step may take on a GPU, and the least it is worth starting with: when the steps
# before it ran long, a step gets what is left of --budget-s after the least of the steps after it.
# The live engine's graphs compile again in its own process (Inductor's on-disk cache from step 2 helps).
LIMITS = {"cuda_tests": (90, 30), "model_speed": (120, 40), "live_engine": (90, 30), "train": (200, 60), "eval": (45, 30)}
# The dry run checks that every step still works, not how fast: its limits leave room for a CPU
# shared with other work (one set of rig model eval took 25 s on a loaded 2-core machine).
DRY_LIMITS = {"cuda_tests": (90, 10), "model_speed": (150, 20), "live_engine": (90, 20), "train": (120, 30), "eval": (90, 20)}
TRAIN_MINUTES = 3.0
PARITY_TOLERANCE = 1e-3  # the image's max abs difference from the torch CPU reference (fp32)
LIVE_FPS, LIVE_P95_MS = 30.0, 100.0  # the live view's target on a GPU at the paper's sizes (issue 34)
# The tree travels with the wheels, and both count against the device machine's 64 MiB.
TRAVEL_LIMIT = 64 * 2**20

# What the steps import beyond the GPU machine's python3 (torch, numpy, OpenCV, onnx, onnxruntime):
# pytest and its needs (step 1; pytest-timeout reads the suite's timeout setting, filelock the test
# exports' lock), matplotlib and its needs (rig train draws its loss curve at each evaluation).
# Pinned where this venv has them, so that what travels is what ran here.
CARRIED = ("pytest", "pluggy", "iniconfig", "pygments", "packaging", "pytest-timeout", "filelock",
           "matplotlib", "contourpy", "cycler", "fonttools", "kiwisolver", "pillow", "pyparsing", "python-dateutil", "tzdata")
# Needs of the carried wheels that the GPU machine's python3 already has.
ON_THE_MACHINE = {"numpy", "torch", "opencv-python", "onnx", "onnxruntime", "typing-extensions", "exceptiongroup", "tomli", "colorama"}


# --- the take and the sizes of each mode ----------------------------------------------------------

def plan(dry: bool) -> dict:
    if dry:
        take = {"size": "320x180", "fps": 10, "seconds": 0.2}
        return {"sizes": ["test"], "variants": [("fp32", "eager"), ("fp32", "compiled"), ("bf16", "eager")],
                "live_size": "test", "repeat": 1, "warmup": 0, "live_seconds": 3.0, "settle_s": 1.0,
                "take": take, "held_out": take, "train_size": "test", "train_steps": 1, "eval_sets": 1}
    # The paper's live view reads 1024x576 sources (1280x720 frames resized) at the cameras' 30 fps;
    # 12 sets replay in a loop. Training reads the same take at the shipped model's (preview) sizes.
    return {"sizes": ["paper", "preview"], "variants": [("fp32", "eager"), ("fp32", "compiled"), ("bf16", "eager"), ("bf16", "compiled")],
            "live_size": "paper", "repeat": 20, "warmup": 3, "live_seconds": 15.0, "settle_s": 3.0,
            "take": {"size": "1280x720", "fps": 30, "seconds": 0.4}, "held_out": {"size": "640x360", "fps": 10, "seconds": 0.3},
            "train_size": None, "train_steps": None, "eval_sets": 3}


# --- carried wheels --------------------------------------------------------------------------------

def prepare(folder: Path, python_versions: list[str]) -> int:
    """Download the carried wheels into `folder` (here, where PyPI is reachable) and say how to run."""
    from importlib import metadata

    folder.mkdir(parents=True, exist_ok=True)
    pins = []
    for name in CARRIED:
        try:
            pins.append(f"{name}=={metadata.version(name)}")
        except metadata.PackageNotFoundError:
            pins.append(name)
    for version in python_versions:
        tag = "cp" + version.replace(".", "")
        cmd = [sys.executable, "-m", "pip", "download", "-q", "--no-deps", "--only-binary=:all:", "--python-version", version,
               "--implementation", "cp", "--abi", tag, "--abi", "abi3", "--abi", "none",
               "--platform", "manylinux_2_28_x86_64", "--platform", "manylinux_2_27_x86_64", "--platform", "manylinux_2_17_x86_64",
               "--platform", "manylinux2014_x86_64", "--platform", "any", "-d", str(folder), *pins]
        print(" ".join(cmd), file=sys.stderr)
        if subprocess.run(cmd).returncode != 0:
            print(f"gpu_check: pip download failed for Python {version}", file=sys.stderr)
            return 1
    wheels = sorted(folder.glob("*.whl"))
    unmet = unmet_needs(wheels, python_versions)
    size = sum(w.stat().st_size for w in wheels)
    tree = tracked_size()
    (folder / "manifest.json").write_text(json.dumps({"prepared": now(), "commit": git_commit(), "python": python_versions,
                                                      "wheels": [w.name for w in wheels], "bytes": size}, indent=1))
    print(f"{len(wheels)} wheels, {size / 2**20:.1f} MiB in {folder}; with the tracked tree ({tree / 2**20:.1f} MiB): "
          f"{(size + tree) / 2**20:.1f} MiB of the device's {TRAVEL_LIMIT / 2**20:.0f} MiB")
    if unmet:
        print(f"gpu_check: the carried wheels need what is neither carried nor on the machine: {', '.join(sorted(unmet))}", file=sys.stderr)
        return 1
    if size + tree > TRAVEL_LIMIT:
        print("gpu_check: too large to travel: carry fewer wheels or fewer Python versions", file=sys.stderr)
        return 1
    rel = os.path.relpath(folder, REPO)
    print("On the GPU machine (device tool: run, with carry=[\"%s\"]):" % rel)
    print(f"    PYTHONUNBUFFERED=1 python3 benchmarks/gpu_check.py --carry {rel} --out $OUT")
    return 0


def norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def wheel_tags(path: Path) -> tuple[str, str, str, str]:
    """(distribution, python tag, abi tag, platform tag) from a wheel's file name."""
    parts = path.name[: -len(".whl")].split("-")
    return norm(parts[0]), parts[-3], parts[-2], parts[-1]


def unmet_needs(wheels: list[Path], python_versions: list[str]) -> set[str]:
    """Requirements of the wheels, on Linux at each target Python, that no carried wheel nor the
    machine provides (markers evaluated by `packaging`, which pip brings wherever --prepare runs)."""
    from packaging.requirements import Requirement

    have = {wheel_tags(w)[0] for w in wheels} | ON_THE_MACHINE
    unmet = set()
    for w in wheels:
        with zipfile.ZipFile(w) as z:
            meta = next(n for n in z.namelist() if n.endswith(".dist-info/METADATA"))
            for line in z.read(meta).decode("utf-8", "replace").splitlines():
                if not line.startswith("Requires-Dist:"):
                    continue
                req = Requirement(line.split(":", 1)[1].strip())
                envs = [{"python_version": v, "python_full_version": v + ".0", "sys_platform": "linux", "platform_system": "Linux",
                         "platform_machine": "x86_64", "os_name": "posix", "extra": ""} for v in python_versions]
                if req.marker is not None and not any(req.marker.evaluate(e) for e in envs):
                    continue
                if norm(req.name) not in have:
                    unmet.add(norm(req.name))
    return unmet


def fits(path: Path) -> bool:
    """Whether this interpreter can use the wheel (tags read the simple way: the carried wheels are
    pure Python or CPython manylinux x86_64 builds)."""
    _, py, abi, plat = wheel_tags(path)
    me = f"cp{sys.version_info.major}{sys.version_info.minor}"
    py_ok = any(t in ("py3", me) or (t.startswith("py3") and len(t) == 3) for t in py.split("."))
    abi_ok = any(a in ("none", "abi3", me) for a in abi.split("."))
    plat_ok = any(p == "any" or (sys.platform.startswith("linux") and p.endswith(platform.machine()) and "linux" in p) for p in plat.split("."))
    return py_ok and abi_ok and plat_ok


def top_levels(z: zipfile.ZipFile) -> set[str]:
    names = set()
    for n in z.namelist():
        first = n.split("/")[0]
        if first.endswith((".dist-info", ".data")) or first == "__pycache__" or first.endswith(".libs"):
            continue
        names.add(first[:-3] if first.endswith(".py") else first.split(".")[0])
    return names


def install_carried(folder: Path, site: Path) -> dict:
    """Unpack into `site` the carried wheels whose packages this python3 lacks (a wheel is a zip of
    its installed files; *.data/purelib and platlib go beside them)."""
    import importlib.util

    report = {"folder": str(folder), "site": str(site), "installed": [], "present": [], "unusable": []}
    manifest = folder / "manifest.json"
    if manifest.is_file():
        report["manifest"] = json.loads(manifest.read_text())
    site.mkdir(parents=True, exist_ok=True)
    for wheel in sorted(folder.glob("*.whl")):
        with zipfile.ZipFile(wheel) as z:
            tops = sorted(top_levels(z))
            if tops and all(importlib.util.find_spec(t) is not None for t in tops):
                report["present"].append(wheel.name)
                continue
            if not fits(wheel):
                report["unusable"].append(wheel.name)
                continue
            for member in z.infolist():
                parts = member.filename.split("/")
                if parts[0].endswith(".data"):
                    if len(parts) < 3 or parts[1] not in ("purelib", "platlib"):
                        continue
                    parts = parts[2:]
                target = site.joinpath(*parts)
                if member.is_dir():
                    target.mkdir(parents=True, exist_ok=True)
                    continue
                target.parent.mkdir(parents=True, exist_ok=True)
                target.write_bytes(z.read(member))
        report["installed"].append(wheel.name)
    return report


# --- the parent: steps as child processes with time limits -----------------------------------------

def now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def git_commit() -> str | None:
    try:
        out = subprocess.run(["git", "-C", str(REPO), "describe", "--always", "--dirty"], capture_output=True, text=True, timeout=10)
        return out.stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        return None


def tracked_size() -> int:
    try:
        out = subprocess.run(["git", "-C", str(REPO), "ls-files", "-z"], capture_output=True, timeout=30).stdout.decode().split("\0")
    except (OSError, subprocess.SubprocessError):
        return 0
    return sum((REPO / p).stat().st_size for p in out if p and (REPO / p).is_file())


def tail(text: str, n: int = 15) -> str:
    return "\n".join(text.strip().splitlines()[-n:])


def last_json(text: str):
    for line in reversed(text.strip().splitlines()):
        line = line.strip()
        if line.startswith("{"):
            try:
                return json.loads(line)
            except json.JSONDecodeError:
                continue
    return None


class Proc:
    """A child process in its own process group: killed whole (its own children too) on timeout."""

    def __init__(self, cmd: list[str], env: dict, log: Path):
        self.cmd, self.log = cmd, log
        self.out = open(log, "w")
        self.started = time.monotonic()
        self.p = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=self.out, stderr=subprocess.STDOUT, start_new_session=True)

    def wait(self, timeout: float) -> tuple[int | None, str]:
        """(exit code, or None when it ran past `timeout` and was killed; its output)."""
        try:
            code = self.p.wait(timeout=max(timeout, 0.1))
        except subprocess.TimeoutExpired:
            self.kill()
            code = None
        self.out.close()
        return code, self.log.read_text(errors="replace")

    def kill(self) -> None:
        for sig, wait in ((signal.SIGTERM, 10), (signal.SIGKILL, 10)):
            try:
                os.killpg(self.p.pid, sig)
            except ProcessLookupError:
                return
            try:
                self.p.wait(timeout=wait)
                return
            except subprocess.TimeoutExpired:
                continue


class Check:
    def __init__(self, args):
        self.args = args
        self.dry = args.dry_run
        self.plan = plan(self.dry)
        self.out = Path(args.out)
        self.out.mkdir(parents=True, exist_ok=True)
        self.work = Path(tempfile.mkdtemp(prefix="gpu-check-"))
        self.limits = DRY_LIMITS if self.dry else LIMITS
        self.started = time.monotonic()
        self.deadline = self.started + args.budget_s
        self.env = dict(os.environ, PYTHONPATH=str(REPO), PYTHONUNBUFFERED="1")
        self.results = {"check": "gpu_check", "started": now(), "device": args.device, "dry_run": self.dry, "commit": git_commit(),
                        "budget_s": args.budget_s, "python": platform.python_version(), "platform": platform.platform(),
                        "plan": self.plan, "steps": {}}
        self.takes: dict[str, Proc] = {}

    def save(self) -> None:
        path = self.out / RESULTS
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps(self.results, indent=1, default=str))
        tmp.replace(path)

    def python(self, *argv) -> list[str]:
        return [sys.executable, *argv]

    def limit(self, name: str) -> float:
        cap, _ = self.limits[name]
        later = STEPS[STEPS.index(name) + 1:]
        reserve = sum(self.limits[s][1] for s in later)
        return min(cap, self.deadline - time.monotonic() - reserve)

    def run(self) -> int:
        if self.args.carry:
            site = Path(self.args.site or self.work / "site")
            try:
                self.results["carry"] = install_carried(Path(self.args.carry), site)
            except (OSError, zipfile.BadZipFile, StopIteration) as exc:
                self.results["carry"] = {"error": f"{type(exc).__name__}: {exc}"}
            self.env["PYTHONPATH"] = f"{REPO}{os.pathsep}{site}"
        self.results["environment"] = self.environment()
        self.save()
        self.start_takes()
        for name in STEPS:
            self.step(name)
        for proc in self.takes.values():
            proc.kill()
        self.results["seconds"] = round(time.monotonic() - self.started, 1)
        line = self.summary()
        self.results["summary"] = line
        self.save()
        (self.out / SUMMARY).write_text(line + "\n")
        shutil.rmtree(self.work, ignore_errors=True)
        print(line)
        return 1 if any(s["status"] == "failed" for s in self.results["steps"].values()) else 0

    def environment(self) -> dict:
        code = ("import json, torch, numpy, cv2, onnxruntime\n"
                "d = {'torch': torch.__version__, 'cuda': torch.version.cuda, 'cuda_available': torch.cuda.is_available(),"
                " 'numpy': numpy.__version__, 'opencv': cv2.__version__, 'onnxruntime': onnxruntime.__version__,"
                " 'ort_providers': onnxruntime.get_available_providers(), 'cpus': __import__('os').cpu_count()}\n"
                "if torch.cuda.is_available():\n"
                "    p = torch.cuda.get_device_properties(0)\n"
                "    d.update(gpu=p.name, gpu_memory_gib=round(p.total_memory / 2**30, 1), capability=f'{p.major}.{p.minor}')\n"
                "print(json.dumps(d))\n")
        try:
            out = subprocess.run(self.python("-c", code), capture_output=True, text=True, timeout=120, env=self.env, cwd=REPO)
            env = last_json(out.stdout) or {"error": tail(out.stderr)}
        except subprocess.TimeoutExpired:
            env = {"error": "python3 -c 'import torch ...' took over 120 s"}
        if shutil.which("nvidia-smi"):
            try:
                env["nvidia_smi"] = subprocess.run(["nvidia-smi", "--query-gpu=name,driver_version,memory.total", "--format=csv,noheader"],
                                                   capture_output=True, text=True, timeout=30).stdout.strip()
            except subprocess.SubprocessError:
                pass
        return env

    def start_takes(self) -> None:
        """Render the simulator takes beside steps 1 and 2 (CPU work: the GPU steps do not feel it)."""
        for key, seed in (("take", 0), ("held_out", 1)):
            t = self.plan[key]
            self.takes[key] = Proc(self.python("-m", "rig", "sim", "dataset", "-o", str(self.work / key), "--takes", "1", "--seed", str(seed),
                                               "--seconds", str(t["seconds"]), "--fps", str(t["fps"]), "--size", t["size"], "--json"),
                                   self.env, self.work / f"{key}.log")

    def take(self, key: str, timeout: float) -> Path:
        proc = self.takes[key]
        code, text = proc.wait(timeout)
        if code != 0:
            raise StepError(f"rig sim dataset ({key}) " + ("ran past the step's time" if code is None else f"exited {code}") + f": {tail(text, 5)}")
        return self.work / key / "take-000"

    def step(self, name: str) -> None:
        rec = {"step": STEPS.index(name) + 1, "status": "failed"}
        self.results["steps"][name] = rec
        limit = self.limit(name)
        rec["limit_s"] = round(limit, 1)
        t0 = time.monotonic()
        try:
            if limit < self.limits[name][1] / 2:
                raise StepError(f"not run: {limit:.0f} s were left of the check's {self.args.budget_s:.0f} s")
            getattr(self, "step_" + name)(rec, t0 + limit)
            if rec["status"] == "failed" and "error" not in rec:
                rec["status"] = "passed"
        except Skip as why:
            rec.update(status="skipped", why=str(why))
        except StepError as exc:
            rec.update(status="failed", error=str(exc))
        except Exception as exc:  # the check's own fault in one step must not lose the others' results
            rec.update(status="failed", error=f"{type(exc).__name__}: {exc}")
        rec["seconds"] = round(time.monotonic() - t0, 1)
        print(f"gpu_check: {name}: {rec['status']} in {rec['seconds']} s" + (f" ({rec.get('why') or rec.get('error')})" if rec["status"] != "passed" else ""),
              file=sys.stderr, flush=True)
        self.save()

    def child(self, rec: dict, name: str, argv: list[str], until: float) -> dict:
        """Run a step's work in `python3 gpu_check.py --step NAME`, which appends its results as JSON
        lines: what it finished before a timeout or a crash is kept."""
        lines = self.work / f"{name}.jsonl"
        cmd = self.python(str(Path(__file__).resolve()), "--step", name, "--device", self.args.device, "--lines", str(lines),
                          *(["--dry-run"] if self.dry else []), *argv)
        code, text = Proc(cmd, self.env, self.work / f"{name}.log").wait(until - time.monotonic())
        found = {}
        if lines.is_file():
            for line in lines.read_text().splitlines():
                found.update(json.loads(line))
        rec.update(found)
        if code is None:
            raise StepError(f"ran past its {rec['limit_s']:.0f} s and was stopped; last output: {tail(text, 8)}")
        if code != 0:
            raise StepError(tail(text))
        return found

    # --- the steps ---------------------------------------------------------------------------------
    def step_cuda_tests(self, rec: dict, until: float) -> None:
        files = sorted(str(p.relative_to(REPO)) for p in (REPO / "tests").rglob("test_*.py") if re.search(r"mark\.cuda\b", p.read_text(errors="replace")))
        rec["files"] = files
        if not files:
            raise Skip("no test is marked cuda")
        xml = self.work / "cuda_tests.xml"
        cmd = self.python("-m", "pytest", "-m", "cuda", "-q", "-p", "no:cacheprovider", "-rfEs", f"--junitxml={xml}", *files)
        rec["command"] = " ".join(cmd[1:])
        code, text = Proc(cmd, self.env, self.work / "cuda_tests.log").wait(until - time.monotonic())
        counts, failures, skips = junit(xml)
        rec["tests"] = counts
        if failures:
            rec["failures"] = failures
        if code is None:
            raise StepError(f"pytest ran past {rec['limit_s']:.0f} s and was stopped: {tail(text, 8)}")
        if code == 5:
            raise Skip(f"pytest -m cuda selected no test in {', '.join(files)}")
        if code != 0 or counts.get("failed") or counts.get("errors") or not counts.get("total"):
            raise StepError(f"pytest exited {code}: {tail(text)}")
        if counts.get("skipped") == counts.get("total"):
            raise Skip(f"{counts['total']} tests collected, all skipped: {sorted(set(skips))[0] if skips else 'see the log'}")

    def step_model_speed(self, rec: dict, until: float) -> None:
        found = self.child(rec, "model_speed", [], until)
        fp32 = [r for r in found.get("runs", []) if r.get("precision") == "fp32"]
        eager = [f"{r['size']}: {r['graphs']}" for r in fp32 if r["variant"] == "compiled" and r.get("graphs") != "compiled"]
        if eager:
            raise StepError(f"the compiled runtime fell back to eager: {'; '.join(eager)}")
        bad = [f"{r['size']} {r['variant']}: {r['max_abs_diff_cpu']:.2e}" for r in fp32 if r.get("max_abs_diff_cpu", 0.0) > PARITY_TOLERANCE]
        if bad:
            raise StepError(f"the image differs from the torch CPU reference by more than {PARITY_TOLERANCE:g}: {'; '.join(bad)}")

    def step_live_engine(self, rec: dict, until: float) -> None:
        take = self.take("take", until - time.monotonic())
        found = self.child(rec, "live_engine", ["--take", str(take)], until)
        if not found.get("frames_out"):
            raise StepError("the engine delivered no frame")
        if self.dry:
            return
        if found.get("graphs") != "compiled":
            raise StepError(f"the runtime's graphs: {found.get('graphs')}")
        fps, p95 = found.get("fps_out") or 0.0, found["latency_ms"]["p95"]
        if fps < LIVE_FPS or p95 is None or p95 > LIVE_P95_MS:
            raise StepError(f"below the target of {LIVE_FPS} fps with p95 <= {LIVE_P95_MS} ms: {fps} fps, p95 {p95} ms")

    def step_train(self, rec: dict, until: float) -> None:
        take = self.take("take", until - time.monotonic())
        run = self.work / "run"
        helps = rig_help(self.env, "train")
        cmd = self.python("-m", "rig", "train", str(take), "-o", str(run), "--json")
        if self.dry:
            # The shipped checkpoint is preview-size; --init takes only a checkpoint of the run's own sizes.
            # One frame set a step: the default batch's step takes 30 s on a 2-core CPU (13 s with one)
            cmd += ["--size", self.plan["train_size"], "--stop-after", str(self.plan["train_steps"]), "--batch", "1"]
            rec["note"] = "dry run: a test-size model from its initial weights (the shipped checkpoint is preview-size)"
        else:
            cmd += ["--init", str(REPO / "models" / "splat-sap-preview.pt")]
            minutes = min(TRAIN_MINUTES, (until - time.monotonic() - 40) / 60.0)  # start-up and the last checkpoint
            if "--max-minutes" in helps:
                cmd += ["--max-minutes", f"{minutes:.2f}"]
            else:
                raise StepError("rig train has no --max-minutes here: the step cannot bound its run")
        if "--device" in helps:
            cmd += ["--device", self.args.device]
        elif not self.dry:
            rec["note"] = "rig train has no --device here: it chose its own"
        rec["command"] = " ".join(cmd[1:])
        code, text = Proc(cmd, self.env, self.work / "train.log").wait(until - time.monotonic())
        summary = last_json(text)
        rec["summary"] = summary
        checkpoint = next((p for p in (run / "model.pt", run / "checkpoint.pt") if p.is_file()), None)
        rec["checkpoint"] = checkpoint.name if checkpoint else None
        if checkpoint:
            self.results["trained"] = str(checkpoint)
        if isinstance(summary, dict):
            rec["steps_per_s"] = summary.get("steps_per_s")
            rec["steps"] = summary.get("steps_this_run", summary.get("steps"))
        if code is None:
            raise StepError(f"rig train ran past {rec['limit_s']:.0f} s and was stopped: {tail(text, 8)}")
        if code != 0 or checkpoint is None:
            raise StepError(f"rig train exited {code}" + ("" if checkpoint else ", no checkpoint written") + f": {tail(text)}")

    def step_eval(self, rec: dict, until: float) -> None:
        trained = self.results.get("trained")
        if not trained:
            raise StepError("not run: step 4's rig train wrote no checkpoint")
        held = self.take("held_out", until - time.monotonic())
        cmd = self.python("-m", "rig", "model", "eval", "--model", trained, "--sequence", str(held), "--max-sets", str(self.plan["eval_sets"]),
                          "--no-references", "--json")
        if "--device" in rig_help(self.env, "model", "eval"):
            cmd += ["--device", self.args.device]
        rec["command"] = " ".join(cmd[1:])
        code, text = Proc(cmd, self.env, self.work / "eval.log").wait(until - time.monotonic())
        rec["figures"] = last_json(text)
        if code is None:
            raise StepError(f"rig model eval ran past {rec['limit_s']:.0f} s and was stopped: {tail(text, 8)}")
        if code != 0:
            raise StepError(f"rig model eval exited {code}: {tail(text)}")

    # --- the summary line --------------------------------------------------------------------------
    def summary(self) -> str:
        env = self.results.get("environment", {})
        card = env.get("gpu") or ("CPU dry run" if self.dry else "no GPU")
        parts = []
        for name, rec in self.results["steps"].items():
            text = f"{name} {rec['status']}"
            fig = brief(name, rec)
            if rec["status"] == "failed":  # the line alone should say what to look at in the JSON
                first = (rec.get("error") or "").strip().splitlines()
                fig = "; ".join(x for x in (fig, first[-1][:100] if first else "") if x)
            if fig:
                text += f" ({fig})"
            parts.append(text)
        counts = {s: sum(1 for r in self.results["steps"].values() if r["status"] == s) for s in ("passed", "skipped", "failed")}
        return (f"gpu_check {self.results['started'][:10]} {card}, torch {env.get('torch')}: " + "; ".join(parts) +
                f" -- {counts['passed']} passed, {counts['skipped']} skipped, {counts['failed']} failed in {self.results['seconds']} s")


class StepError(Exception):
    pass


class Skip(Exception):
    pass


def rig_help(env: dict, *command: str) -> str:
    try:
        return subprocess.run([sys.executable, "-m", "rig", *command, "--help"], capture_output=True, text=True, env=env, cwd=REPO, timeout=60).stdout
    except subprocess.TimeoutExpired:
        return ""


def junit(path: Path) -> tuple[dict, list, list]:
    """(counts, failed tests with their message, skip reasons) from pytest's JUnit XML."""
    import xml.etree.ElementTree as ET

    if not path.is_file():
        return {}, [], []
    root = ET.parse(path).getroot()
    suite = root if root.tag == "testsuite" else root.find("testsuite")
    counts = {k: int(suite.get(k, 0)) for k in ("tests", "failures", "errors", "skipped")}
    counts = {"total": counts["tests"], "failed": counts["failures"], "errors": counts["errors"], "skipped": counts["skipped"],
              "passed": counts["tests"] - counts["failures"] - counts["errors"] - counts["skipped"]}
    failures, skips = [], []
    for case in suite.iter("testcase"):
        for kind in ("failure", "error"):
            el = case.find(kind)
            if el is not None:
                failures.append({"test": f"{case.get('classname')}::{case.get('name')}", "message": tail(el.get("message", "") or el.text or "", 5)})
        el = case.find("skipped")
        if el is not None:
            skips.append(el.get("message", ""))
    return counts, failures, skips


def brief(name: str, rec: dict) -> str:
    if name == "cuda_tests" and rec.get("tests") and rec["status"] != "skipped":
        t = rec["tests"]
        return f"{t['passed']}/{t['total']} passed"
    if name == "model_speed" and rec.get("runs"):
        out = []
        for r in rec["runs"]:
            if r["precision"] == "fp32":
                out.append(f"{r['size']} {r['variant']} {r['stage1_ms']:.1f}+{r['view_ms']:.1f} ms")
        return ", ".join(out)
    if name == "live_engine" and rec.get("latency_ms"):
        lat = rec["latency_ms"]
        return f"{rec.get('fps_out')} fps out of {rec.get('fps_in')} in, p50 {lat['p50']} ms, p95 {lat['p95']} ms"
    if name == "train" and rec.get("steps") is not None:
        return f"{rec['steps']} steps, {rec.get('steps_per_s')} steps/s"
    if name == "eval" and isinstance(rec.get("figures"), dict):
        f = rec["figures"]
        psnr = find_key(f, "psnr")
        return f"PSNR {psnr:.2f} dB" if isinstance(psnr, (int, float)) else ""
    return ""


def find_key(d, key: str):
    """The first value under `key` anywhere in nested dicts (the eval's JSON nests its figures)."""
    if isinstance(d, dict):
        if key in d and isinstance(d[key], (int, float)):
            return d[key]
        for v in d.values():
            found = find_key(v, key)
            if found is not None:
                return found
    return None


# --- the children: a step's work in its own process -----------------------------------------------

def emit(lines: Path, **record) -> None:
    with open(lines, "a") as f:
        f.write(json.dumps(record, default=str) + "\n")


SOURCES = ("left_image", "right_image", "left_K", "right_K", "left_pose", "right_pose")


def dry_compiler():
    """On the CPU (the dry run) Inductor would build C++ for minutes: TorchDynamo's capture with the
    eager backend keeps the compiled path exercised in seconds."""
    import torch

    return lambda fn: torch.compile(fn, backend="eager", dynamic=False)


def child_model_speed(args) -> None:
    """Stage 1 and the view through the torch live runtime (inference.gpu_runtime), eager and
    compiled (its CUDA graphs), fp32 and bf16 autocast, against the whole model on the CPU."""
    import contextlib

    import torch

    from inference.device import resolve_device
    from inference.gpu_runtime import TorchLivePipeline
    from inference.runtime.synthetic import example_inputs

    device = resolve_device(args.device)
    p = plan(args.dry_run)
    # On the GPU fp32 measures what the live view runs: the runtime's own compilers (None).
    base = dry_compiler() if device.type == "cpu" else (lambda fn: torch.compile(fn, dynamic=False, options={"freezing": True}))
    emit(args.lines, compiler="dynamo, eager backend (CPU dry run)" if device.type == "cpu" else "inductor, captured as CUDA graphs",
         repeat=p["repeat"], warmup=p["warmup"], runs=[])
    runs, references, images = [], {}, {}
    # fp32 at every size before bf16 (a measured variant only): what a time limit cuts is the least needed.
    order = [(precision, variant, size) for precision in ("fp32", "bf16") for size in p["sizes"] for (pr, variant) in p["variants"] if pr == precision]
    for precision, variant, size in order:
        if size not in references:
            reference_pipe = TorchLivePipeline(None, "cpu", size, compile=False)
            example = example_inputs(reference_pipe.sizes, False, seed=0)
            with torch.no_grad():
                want = reference_pipe.net(*[torch.from_numpy(example.arrays[n]) for n in reference_pipe.net.input_names])[0][0]
            references[size] = (example, want)
            del reference_pipe
        example, reference = references[size]
        bf16 = precision == "bf16"

        def autocast():
            return torch.autocast(device.type, dtype=torch.bfloat16) if bf16 else contextlib.nullcontext()

        def compiler(fn):
            if not bf16:
                return base(fn)

            def under_autocast(*a):
                with autocast():
                    return fn(*a)
            return base(under_autocast)

        t0 = time.perf_counter()
        # bf16 is a measured variant: the runtime's own check against eager fp32 would refuse it.
        own = device.type == "cuda" and not bf16
        pipe = TorchLivePipeline(None, device, size, compile=variant == "compiled", compiler=None if own else compiler,
                                 check_tolerance=float("inf") if bf16 else PARITY_TOLERANCE)
        pipe.warm(background=False)
        row = {"size": size, "sizes": pipe.sizes.describe(), "precision": precision, "variant": variant, "graphs": pipe.graphs,
               "ready_s": round(time.perf_counter() - t0, 2), "compile_s": pipe.compile_s}
        feeds = {n: example.arrays[n] for n in SOURCES}

        def once():
            with autocast():
                s1 = pipe.stage1(feeds)
                # render keeps the image a tensor (under bf16 autocast it may be one numpy has no type for).
                view = pipe.render(s1, feeds, example.target)
            return view.image_device, pipe.stage1_ms, pipe.view_ms

        for _ in range(p["warmup"]):
            once()
        s1_ms, view_ms = [], []
        for _ in range(p["repeat"]):
            image, a, b = once()
            s1_ms.append(a)
            view_ms.append(b)
        image = image.float().cpu()
        images[(size, precision, variant)] = image
        row.update(stage1_ms=round(statistics.median(s1_ms), 2), view_ms=round(statistics.median(view_ms), 2),
                   stage1_ms_min=round(min(s1_ms), 2), view_ms_min=round(min(view_ms), 2),
                   max_abs_diff_cpu=float((image - reference).abs().max()), graphs=pipe.graphs)
        row["fps_one_viewer"] = round(1000.0 / (row["stage1_ms"] + row["view_ms"]), 1)
        if variant == "compiled" and (size, precision, "eager") in images:
            row["max_abs_diff_eager"] = float((image - images[(size, precision, "eager")]).abs().max())
        runs.append(row)
        emit(args.lines, runs=runs)
        del pipe
        if device.type == "cuda":
            torch.cuda.empty_cache()


def child_live_engine(args) -> None:
    """LiveEngine on a replayed take with the torch runtime: frames are served eager while the graphs
    compile; the figures are taken once they serve (and the loop has settled)."""
    from inference.device import resolve_device
    from inference.gpu_runtime import TorchLivePipeline
    from rig.live.engine import LiveEngine
    from rig.live.source import ReplaySource

    device = resolve_device(args.device)
    p = plan(args.dry_run)
    source = ReplaySource(args.take, "left", "right")
    rig = source.sequence.calibration or source.sequence.ground_truth
    t0 = time.perf_counter()
    # The dry run stays eager: step 2 exercises the compiled path, and a second capture costs seconds.
    pipe = TorchLivePipeline(None, device, p["live_size"], compile=not args.dry_run)
    pipe.warm(background=True)
    engine = LiveEngine(source, rig, "left", "right", pipe)
    latencies, first_frame_s, compiled_s = [], None, None
    with engine:
        viewer = engine.add_viewer({"type": "viewpoint", "t": 0.5})
        end = time.monotonic() + 600.0
        counted_from = None
        while time.monotonic() < end:
            f = viewer.next_frame(0.05)
            if f is not None:
                viewer.acknowledge(f.set_index, f.viewpoint_id)
                if first_frame_s is None:
                    first_frame_s = round(time.perf_counter() - t0, 2)
            if compiled_s is None and pipe.graphs not in ("compiling", "compile not started"):
                compiled_s = round(time.perf_counter() - t0, 2)
                end = time.monotonic() + p["settle_s"] + p["live_seconds"]
                settle_end = time.monotonic() + p["settle_s"]
                emit(args.lines, graphs=pipe.graphs, first_frame_s=first_frame_s, graphs_ready_s=compiled_s)
            if compiled_s is not None and time.monotonic() >= settle_end:
                if counted_from is None:
                    counted_from = (time.monotonic(), engine.sets_in)
                elif f is not None:
                    # Exposure (the set's capture time) to taken and acknowledged, as the engine counts
                    # it, but over the settled window alone (the engine's window spans the eager start).
                    latencies.append((time.monotonic_ns() - f.capture_ns) / 1e6)
        status = engine.status()
    span = time.monotonic() - counted_from[0] if counted_from else 0.0
    ordered = sorted(latencies)

    def pct(q):
        return round(ordered[min(len(ordered) - 1, int(q * len(ordered)))], 1) if ordered else None

    emit(args.lines, status_figures=status, frames_out=len(latencies), first_frame_s=first_frame_s, measured_s=round(span, 1), runtime=pipe.runtime_status(),
         fps_out=round(len(latencies) / span, 2) if span else 0.0, latency_ms={"p50": pct(0.5), "p95": pct(0.95)},
         fps_in=round((engine.sets_in - counted_from[1]) / span, 2) if span else 0.0)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=os.environ.get("OUT"), help="results folder (default: $OUT)")
    ap.add_argument("--device", default="cuda", help="cuda (default) or cpu")
    ap.add_argument("--dry-run", action="store_true", help="tiny sizes and a few seconds a step (the test suite runs it on the CPU)")
    ap.add_argument("--carry", help="folder of carried wheels (made with --prepare): those this python3 lacks are unpacked first")
    ap.add_argument("--site", help="where to unpack them (default: a temporary folder)")
    ap.add_argument("--budget-s", type=float, help="seconds for all steps (default 450; dry run 600)")
    ap.add_argument("--prepare", metavar="DIR", help="download the wheels to carry into DIR and print the device command line")
    ap.add_argument("--python-version", nargs="+", default=["3.12"], help="with --prepare: the GPU machine's Python (default 3.12)")
    ap.add_argument("--step", choices=("model_speed", "live_engine"), help=argparse.SUPPRESS)
    ap.add_argument("--lines", type=Path, help=argparse.SUPPRESS)
    ap.add_argument("--take", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.prepare:
        return prepare(Path(args.prepare).resolve(), args.python_version)
    if args.step:
        sys.path.insert(0, str(REPO))
        {"model_speed": child_model_speed, "live_engine": child_live_engine}[args.step](args)
        return 0
    if args.device not in ("cuda", "cpu"):
        print(f"gpu_check: --device {args.device}: give cuda or cpu", file=sys.stderr)
        return 2
    if not args.out:
        print("gpu_check: give --out DIR (or set OUT)", file=sys.stderr)
        return 2
    if args.carry and not Path(args.carry).is_dir():
        print(f"gpu_check: --carry {args.carry}: no such folder (make it here with --prepare {args.carry})", file=sys.stderr)
        return 2
    if args.budget_s is None:
        args.budget_s = 600.0 if args.dry_run else 450.0
    return Check(args).run()


if __name__ == "__main__":
    sys.exit(main())
