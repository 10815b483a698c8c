"""One process of a training run (`rig train`): the device and its checks, torch's threads, the
data-parallel group when torchrun started several processes, the MASt3R weights' record, then the
Trainer. The data is any training set with the TrainingSet interface (rig.storage.dataset).
"""
from __future__ import annotations

import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

from inference.errors import InferenceError


def rank() -> int:
    """This process's rank in the torchrun group (0 alone): rank 0 writes and reports."""
    return int(os.environ.get("RANK", "0"))


def world_size() -> int:
    return int(os.environ.get("WORLD_SIZE", "1"))


def elastic_restart(out: Path) -> bool:
    """Whether this process is a worker torchrun started again (`--max-restarts`, a node that came
    back) for the run in `out`: a checkpoint there written under this rendezvous id."""
    import json

    run_id = os.environ.get("TORCHELASTIC_RUN_ID")
    if not run_id or world_size() < 2 or not (Path(out) / "checkpoint.pt").is_file():
        return False
    try:
        return json.loads((Path(out) / "train.json").read_text()).get("elastic_run_id") == run_id
    except (OSError, ValueError, AttributeError):
        return False


@dataclass
class RunOptions:
    """How to run, as `rig train`'s options give it (None: the default)."""

    resume: bool = False
    init: Optional[Path] = None  # a checkpoint whose weights a new run starts from
    weights: Optional[Path] = None  # the MASt3R checkpoint a new run's backbone loads
    device: Optional[str] = None  # cpu | cuda[:N]; default CUDA when torch sees a GPU
    precision: str = "fp32"
    workers: Optional[int] = None  # DataLoader processes; default 0 on the CPU, up to 4 on CUDA
    cache_mb: Optional[float] = None
    threads: Optional[int] = None  # torch threads per process; default the cores shared among this machine's processes
    stop_after: Optional[int] = None
    max_minutes: Optional[float] = None
    checkpoint_minutes: Optional[float] = None


def _cpu_bf16() -> bool:
    """Whether autocast can run bfloat16 matrix products on this CPU (one tiny product, once)."""
    import torch

    try:
        with torch.autocast("cpu", dtype=torch.bfloat16):
            return (torch.ones(2, 2) @ torch.ones(2, 2)).dtype == torch.bfloat16
    except RuntimeError:
        return False


def _backbone_weights(cfg, weights: Optional[Path]) -> Optional[dict]:
    """With MASt3R weights: the model configured for their depths and their record; the licence note
    (rank 0) either way a MASt3R backbone is trained."""
    if weights is not None:
        from inference.model.checkpoint import backbone_weights_record, configure_for_weights
        from inference.model.mast3r_weights import LICENCE, read_weights

        # The depths the weights' file records (the full checkpoint: 24 + 12 blocks).
        cfg.model = configure_for_weights(cfg.model, read_weights(weights))
        if rank() == 0:
            print(f"note: loading {weights}: {LICENCE}", file=sys.stderr)
        return backbone_weights_record(weights)
    if cfg.model.backbone.kind == "mast3r" and rank() == 0:
        from inference.model.mast3r_weights import LICENCE

        print(f"note: the checkpoint holds MASt3R weights: {LICENCE}", file=sys.stderr)
    return None


GROUP_STORE_KEY = "rig/group_store"  # in torchrun's agent store: "PORT NONCE" of rank 0's beacon for this attempt
GROUP_TIMEOUT_S = 300.0


def _init_group(dist, backend: str) -> None:
    """The process group. Under torchrun's agent store (c10d rendezvous) each attempt's group keeps its
    keys under a name rank 0 draws for it. The agent store outlives a failed attempt, and torch names
    each attempt's keys by the restart count, which each agent counts for itself: a node whose worker
    died counts a restart, the other node, whose agent restarts its workers because a node waits to
    join, does not (pytorch/pytorch#108158, #135712). Their workers then looked for each other under
    different names and waited until they timed out. Rank 0 publishes its name in the agent store
    with the port of a small store of its own (a beacon) that answers with the same name: an earlier
    attempt's entry names a beacon that is gone, and the others read the entry again until rank 0's
    is there. The group itself lives in the agent store, which outlives every worker."""
    import datetime
    import secrets
    import time

    if os.environ.get("TORCHELASTIC_USE_AGENT_STORE") != "True":
        dist.init_process_group(backend)
        return
    addr, timeout = os.environ["MASTER_ADDR"], datetime.timedelta(seconds=GROUP_TIMEOUT_S)
    agent = dist.TCPStore(addr, int(os.environ["MASTER_PORT"]), world_size(), is_master=False, timeout=timeout)
    global _BEACON
    if rank() == 0:
        # rank 0 runs on the node that hosts the agent store, so MASTER_ADDR reaches its beacon too
        name = secrets.token_hex(8)
        _BEACON = dist.TCPStore(addr, 0, 1, is_master=True, timeout=timeout, wait_for_workers=False)
        _BEACON.set("name", name)
        agent.set(GROUP_STORE_KEY, f"{_BEACON.port} {name}")
    else:
        name = _attempt_name(dist, agent, addr, time.monotonic() + GROUP_TIMEOUT_S)
    dist.init_process_group(backend, store=dist.PrefixStore(f"rig/attempt/{name}", agent), rank=rank(), world_size=world_size(),
                            timeout=timeout)


_BEACON = None  # rank 0's beacon store, kept until the group is gone


def _release_beacon() -> None:
    """Stop rank 0's beacon with the group rather than in the interpreter's teardown, which destroys
    objects in no set order (a worker that left its group to the teardown aborted there: "terminate
    called without an active exception")."""
    global _BEACON
    _BEACON = None


def _attempt_name(dist, agent, addr: str, deadline: float) -> str:
    """The name rank 0 drew for this attempt (see _init_group): the entry in the agent store, read
    again until the beacon it names answers with the same name."""
    import datetime
    import time

    while True:
        port, name = agent.get(GROUP_STORE_KEY).decode().split()
        try:
            beacon = dist.TCPStore(addr, int(port), 1, is_master=False, timeout=datetime.timedelta(seconds=3))
            if beacon.get("name").decode() == name:
                return name
        except (RuntimeError, dist.DistStoreError):  # refused or timed out: the entry was an earlier attempt's
            pass
        if time.monotonic() > deadline:
            raise InferenceError(f"rig train: rank 0 of this attempt did not answer within {GROUP_TIMEOUT_S:.0f} s")
        time.sleep(0.5)


def train(cfg, data, out: Path, opts: RunOptions, progress: Optional[Callable[[int, int, dict], None]] = None) -> dict:
    """Train `cfg` on `data` into `out` (this process's share under torchrun); the trainer's summary
    with the device it ran on."""
    import torch
    import torch.distributed as dist

    from inference.device import describe as describe_device, resolve_device
    from inference.train.trainer import DEFAULT_CACHE_MB, Trainer

    device = resolve_device(opts.device)  # --device cuda without a GPU: one line, exit 2
    if opts.precision == "bf16" and device.type == "cpu" and not _cpu_bf16():
        raise InferenceError("--precision bf16: this CPU has no bfloat16 arithmetic torch can use; give --precision fp32")
    workers = opts.workers if opts.workers is not None else (min(4, max(0, (os.cpu_count() or 1) - 1)) if device.type == "cuda" else 0)
    weights_record = _backbone_weights(cfg, opts.weights)

    world = world_size()
    torch.set_num_threads(opts.threads or max(1, (os.cpu_count() or 1) // max(1, int(os.environ.get("LOCAL_WORLD_SIZE", world)))))
    resume = opts.resume
    if world > 1:
        _init_group(dist, "nccl" if device.type == "cuda" else "gloo")
        # rank 0 decides whether the run continues (its folder holds the checkpoint: --resume, or
        # torchrun starting the workers again after one failed) and tells the others
        decided = [bool(opts.resume or elastic_restart(out))] if rank() == 0 else [None]
        dist.broadcast_object_list(decided, src=0)
        resume = bool(decided[0])
    try:
        describe = {"sequences": data.roots, "frame_sets": len(data), "sources": [data.left, data.right],
                    "supervision": data.supervision, "processes": world}
        if world > 1 and os.environ.get("TORCHELASTIC_RUN_ID"):
            describe["elastic_run_id"] = os.environ["TORCHELASTIC_RUN_ID"]
        if opts.init is not None:
            describe["init"] = str(opts.init)
        if weights_record is not None:
            describe["backbone_weights"] = weights_record
        trainer = Trainer(cfg, data, out, resume=resume, progress=progress, describe=describe, init=opts.init,
                          backbone_weights=opts.weights, device=device, precision=opts.precision, workers=workers,
                          cache_mb=DEFAULT_CACHE_MB if opts.cache_mb is None else opts.cache_mb)
        summary = trainer.run(stop_after=opts.stop_after, max_minutes=opts.max_minutes, checkpoint_minutes=opts.checkpoint_minutes)
        summary["device"] = describe_device(trainer.device)
    finally:
        if world > 1 and dist.is_initialized():
            dist.destroy_process_group()
        _release_beacon()
    return summary
