"""`rig doctor -c RIG.toml`: is this host ready for this rig? (rig/doctor/; docs/venue.md)"""
from __future__ import annotations

import argparse
import json
import os
import signal
from pathlib import Path

FIX_SCRIPT_HEAD = "#!/usr/bin/env bash\n# Fixes `rig doctor` proposes"
BENCH_MAX_BYTES = 16 << 20  # `rig model bench --json` writes a few kilobytes


def register(sub) -> None:
    p = sub.add_parser("doctor", help="check this host for a rig: USB, network, devices, memory, disk, compute",
                       description="Checks this host for the rig the config describes, one line per check: ok, warn or fail, "
                                   "the measured value, what the rig needs, and the command that fixes it. It reads and "
                                   "measures (a short write test in the output folder, removed after) and never changes the "
                                   "host. Exit 0 when nothing fails, 1 when a check fails, 2 on bad input (docs/venue.md).")
    p.add_argument("-c", "--config", type=Path, required=True, help="rig configuration (TOML)")
    p.add_argument("--output", type=Path, metavar="DIR",
                   help="where the takes will go: free space and write rate are measured there (default: the config's storage)")
    p.add_argument("--minutes", type=float, default=10.0, metavar="M",
                   help="the longest take planned: the free space must hold it (default 10)")
    p.add_argument("--bench", type=Path, metavar="FILE",
                   help="`rig model bench --json` output measured on this host: the live view's reachable rate")
    p.add_argument("--write-test-mb", type=int, default=256, metavar="MB",
                   help="most MB the write test writes (default 256; it also stops after 3 s)")
    p.add_argument("--fix-script", type=Path, metavar="FILE", help="write the fixes as a bash script to review and run")
    p.add_argument("--root", type=Path, default=Path("/"), metavar="DIR",
                   help="read /proc, /sys, /etc and /dev under DIR instead of / (a copy of another host's)")
    p.add_argument("--json", action="store_true", help="print one JSON object: verdict, counts, checks")
    p.set_defaults(func=cmd_doctor)


def _check_inputs(args: argparse.Namespace):
    """Every argument checked before any measurement: ConfigError (exit 2, one line) on a bad one."""
    from rig.config import load_config
    from rig.errors import ConfigError

    if not (args.minutes > 0 and args.minutes < 1e6):
        raise ConfigError(f"--minutes must be a positive number of minutes, got {args.minutes}")
    if not 1 <= args.write_test_mb <= 65536:
        raise ConfigError(f"--write-test-mb must be between 1 and 65536, got {args.write_test_mb}")
    if not args.root.is_dir():
        raise ConfigError(f"--root {args.root}: not a folder")
    cfg = load_config(args.config, check_calibration=False)  # a missing calibration is no host problem
    output = args.output if args.output is not None else cfg.resolve(cfg.storage)
    if output.exists() and not output.is_dir():
        raise ConfigError(f"--output {output}: is a file, not a folder")
    from rig.doctor.space import existing

    above = existing(output)
    if not above.is_dir():  # a take folder cannot be made under a file
        raise ConfigError(f"--output {output}: {above} is a file, not a folder")
    bench = None
    if args.bench is not None:
        from rig.doctor.compute import bench_rate

        try:
            with open(args.bench, "rb") as f:  # bounded: a device (/dev/zero) never ends
                data = f.read(BENCH_MAX_BYTES + 1)
            if len(data) > BENCH_MAX_BYTES:
                raise ValueError(f"over {BENCH_MAX_BYTES >> 20} MiB")
            bench = json.loads(data.decode())
            bench_rate(bench)
        except OSError as exc:
            raise ConfigError(f"--bench {args.bench}: cannot read ({exc.strerror})") from None
        except (ValueError, AttributeError, TypeError, OverflowError) as exc:
            raise ConfigError(f"--bench {args.bench}: not `rig model bench --json` output ({exc})") from None
    fix = args.fix_script
    if fix is not None:
        if fix.is_dir():
            raise ConfigError(f"--fix-script {fix}: is a folder; name a file")
        if not fix.parent.is_dir():
            raise ConfigError(f"--fix-script {fix}: folder {fix.parent} does not exist")
        if fix.exists() and not fix.is_file():  # a device or a pipe: reading it could block or never end
            raise ConfigError(f"--fix-script {fix}: not a regular file; name a file")
        if fix.exists():
            try:
                with open(fix, "rb") as f:
                    head = f.read(len(FIX_SCRIPT_HEAD.encode())).decode(errors="replace")
            except OSError:
                head = ""
            if head != FIX_SCRIPT_HEAD:  # only an earlier fix script is replaced, never another file
                raise ConfigError(f"--fix-script {fix}: exists and is not a fix script of rig doctor; name another file")
        if not os.access(fix.parent, os.W_OK):
            raise ConfigError(f"--fix-script {fix}: cannot write in {fix.parent}")
    return cfg, output, bench


def _stop_on_sigterm(signum, frame) -> None:
    raise KeyboardInterrupt


def cmd_doctor(args: argparse.Namespace) -> int:
    from common.files import atomic_write_bytes
    from rig.commands._output import emit_json
    from rig.doctor import run_checks
    from rig.doctor.check import FAIL, worst
    from rig.doctor.host import Host
    from rig.doctor.report import fix_script, text_lines, to_json

    cfg, output, bench = _check_inputs(args)
    # `kill` (a time limit, a service manager) ends the doctor as Ctrl-C does: the write test's file is removed
    signal.signal(signal.SIGTERM, _stop_on_sigterm)
    checks = run_checks(cfg, Host(args.root), output=output, minutes=args.minutes, bench=bench, bench_path=args.bench,
                        test_bytes=args.write_test_mb << 20)
    config = str(cfg.path.resolve()) if cfg.path else None
    if args.fix_script is not None:
        atomic_write_bytes(args.fix_script, fix_script(checks, cfg.name, config).encode())
        args.fix_script.chmod(0o755)
    if args.json:
        doc = to_json(checks, cfg.name, config)
        if args.fix_script is not None:
            doc["fix_script"] = str(args.fix_script)
        emit_json(doc)
    else:
        print("\n".join(text_lines(checks)))
        if args.fix_script is not None:
            print(f"fixes written to {args.fix_script} (review it, then: bash {args.fix_script})")
    return 1 if worst(checks) == FAIL else 0
