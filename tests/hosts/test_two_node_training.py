"""Two-node training on two hosts (tests/hosts/netns.py): `torchrun --nnodes 2 --max-restarts 1`
with c10d rendezvous on hostA's address and the gloo backend over the veth pair, one process per node,
trains the model on a small simulated take. Node B's training process is killed with kill -9 mid-run:
torchrun starts both nodes' workers again, they go on from the last checkpoint, and the run ends with
the same losses and weights as one uninterrupted process on the same global batch. Both nodes started
again by hand under the same rendezvous id continue the run instead of refusing its folder."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from simulator.takes import write_take
from tests.hosts.netns import TwoHosts, available
from tests.rig.cli_helpers import REPO

WHY = available()
pytestmark = [pytest.mark.skipif(WHY is not None, reason=f"two hosts need network namespaces: {WHY}"), pytest.mark.slow,
              pytest.mark.timeout(600)]
SMALL = ["--size", "test", "--batch", "2", "--eval-every", "100", "--threads", "1"]
LIGHT = {"supervision_per_step": 1, "eval_sets": 1}
# what the two-process run may differ by: the gradients' all-reduce sums in another order
TOLERANCE = 1e-5


@pytest.fixture(scope="module")
def take(tmp_path_factory) -> Path:
    return Path(write_take(tmp_path_factory.mktemp("take") / "take", seed=300, seconds=0.4, fps=10, size=(320, 180))["out"])


def env() -> dict:
    return {k: v for k, v in os.environ.items() if k not in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")} | {"OMP_NUM_THREADS": "1"}


def torchrun(hosts: TwoHosts, node: str, port: int, run_id: str, argv: list, log: Path, restarts: int = 0) -> subprocess.Popen:
    """torchrun on `node`; its output goes to LOG.out and LOG.err (files: gloo's and torchrun's logs
    would fill a pipe nobody reads and stall the run)."""
    dev = hosts.dev[node]
    return hosts.popen(node, ["env", f"GLOO_SOCKET_IFNAME={dev}", sys.executable, "-m", "torch.distributed.run", "--nnodes", "2",
                              "--nproc-per-node", "1", "--rdzv-backend", "c10d", "--rdzv-endpoint", f"{hosts.addr['A']}:{port}",
                              "--rdzv-id", run_id, "--max-restarts", str(restarts), "--monitor-interval", "0.5",
                              # the store runs on hostA: torchrun cannot tell from the host name that its address is A's
                              "--rdzv-conf", f"is_host={'true' if node == 'A' else 'false'}",
                              # the address the other node reaches this one at (else the machine's name, outside the namespace)
                              "--local-addr", hosts.addr[node],
                              "-m", "rig", "train", *map(str, argv)],
                       cwd=REPO, env=env(), stdout=open(f"{log}.out", "w"), stderr=open(f"{log}.err", "w"))


def losses(run: Path) -> list[tuple[int, float]]:
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    return [(m["step"], m["loss"]) for m in rows if not m.get("eval")]


def weights(run: Path) -> dict:
    return torch.load(run / "model.pt", weights_only=True)["state_dict"]


def max_diff(a: dict, b: dict) -> float:
    return max(float((a[k] - b[k]).abs().max()) for k in a if a[k].is_floating_point())


def one_process(take: Path, light: Path, out: Path, steps: int) -> None:
    argv = ["train", take, "-o", out, *SMALL, "--config", light, "--stage1-steps", steps, "--stage2-steps", 0]
    r = subprocess.run([sys.executable, "-m", "rig", *map(str, argv)], cwd=REPO, env=env(), capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]


def two_nodes(args: list, port: int, logs: Path, tag: str, kill_after: int = 0) -> int:
    """`rig train ARGS` on both hosts under rendezvous id two-nodes (`--max-restarts 1`); both must
    succeed (logs in LOGS/A{tag}.err, B{tag}.err). With `kill_after`, node B's training process is
    killed with kill -9 once a step past it is logged; returns the last step logged before the kill."""
    import signal
    import time

    killed_at = 0
    out = Path(args[args.index("-o") + 1])
    with TwoHosts() as hosts:
        a = torchrun(hosts, "A", port, "two-nodes", args, logs / f"A{tag}", restarts=1)
        b = torchrun(hosts, "B", port, "two-nodes", args, logs / f"B{tag}", restarts=1)
        if kill_after:
            deadline = time.monotonic() + 400
            while not (out / "metrics.jsonl").exists() or max((s for s, _ in losses(out)), default=0) < kill_after:
                assert a.poll() is None and b.poll() is None and time.monotonic() < deadline, (logs / f"A{tag}.err").read_text()[-2000:]
                time.sleep(0.2)
            killed_at = max(s for s, _ in losses(out))
            os.kill(worker_of(b), signal.SIGKILL)
        a.wait(500)
        b.wait(60)
    assert not hosts.exists(), "a namespace was left behind"
    assert a.returncode == 0 and b.returncode == 0, ((logs / f"A{tag}.err").read_text()[-2000:], (logs / f"B{tag}.err").read_text()[-2000:])
    return killed_at


def worker_of(agent: subprocess.Popen, timeout: float = 120) -> int:
    """The pid of the training process torchrun `agent` runs (through `ip netns exec` and `env`)."""
    import time

    deadline = time.monotonic() + timeout
    while True:
        pids = [agent.pid]
        for _ in range(6):  # ip netns exec -> env -> torchrun -> the worker
            kids = []
            for p in pids:
                try:
                    kids += [int(k) for k in open(f"/proc/{p}/task/{p}/children").read().split()]
                except OSError:
                    pass
            if not kids:
                break
            pids = kids
        workers = [p for p in pids if "rig" in open(f"/proc/{p}/cmdline").read() and p != agent.pid] if pids else []
        if workers:
            return workers[0]
        assert time.monotonic() < deadline, "torchrun started no worker"
        time.sleep(0.2)


def test_two_nodes_train_as_one_process_and_a_killed_node_resumes_from_its_checkpoint(take, tmp_path):
    config = tmp_path / "train.json"
    config.write_text(json.dumps({**LIGHT, "checkpoint_every": 2}))
    steps = 5
    one_process(take, config, tmp_path / "one", steps)
    two = tmp_path / "two"
    args = [take, "-o", two, *SMALL, "--config", config, "--stage1-steps", steps, "--stage2-steps", 0]
    # node B's training process killed after step 3: torchrun (--max-restarts 1) starts both nodes'
    # workers again and they go on from step 2's checkpoint
    killed_at = two_nodes(args, 29411, tmp_path, "", kill_after=3)
    checkpoint_step = killed_at - killed_at % 2
    print(f"killed after step {killed_at}; resumed from the checkpoint of step {checkpoint_step}: {killed_at - checkpoint_step} steps lost")
    info = json.loads((two / "train.json").read_text())
    assert info["processes"] == 2 and info["elastic_run_id"] == "two-nodes"
    # every step logged once, and the same losses and weights as one uninterrupted process on the
    # same global batch (batches are drawn by (seed, stage, step): a resumed run sees the same)
    l1, l2 = losses(tmp_path / "one"), losses(two)
    assert [s for s, _ in l2] == list(range(1, steps + 1)), l2
    assert max(abs(x - y) / max(abs(x), 1e-9) for (_, x), (_, y) in zip(l1, l2)) < TOLERANCE, (l1, l2)
    assert max_diff(weights(tmp_path / "one"), weights(two)) < TOLERANCE

    # the crew starts both nodes again with the same command lines and a longer schedule: it goes on
    more = [take, "-o", two, *SMALL, "--config", config, "--stage1-steps", steps + 1, "--stage2-steps", 0]
    two_nodes(more, 29412, tmp_path, "2")
    assert [s for s, _ in losses(two)] == list(range(1, steps + 2))
