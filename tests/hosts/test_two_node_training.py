"""Two-node training on two hosts (tests/hosts/netns.py): `torchrun --nnodes 2` with c10d rendezvous
on hostA's address and the gloo backend over the veth pair, one process per node, trains the model on
a small simulated take: the same losses and weights as one process on the same global batch. Started
again under the same rendezvous id (as torchrun --max-restarts starts the workers again after one
failed), the same command line continues the run from its checkpoint instead of refusing its folder,
rank 1 taking rank 0's state."""
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


@pytest.fixture(scope="module")
def light(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("config") / "train.json"
    path.write_text(json.dumps(LIGHT))
    return path


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


def two_nodes(args: list, port: int, logs: Path, tag: str) -> None:
    """`rig train ARGS` on both hosts under rendezvous id two-nodes; both must succeed (logs in LOGS/A{tag}.err, B{tag}.err)."""
    with TwoHosts() as hosts:
        a = torchrun(hosts, "A", port, "two-nodes", args, logs / f"A{tag}")
        b = torchrun(hosts, "B", port, "two-nodes", args, logs / f"B{tag}")
        a.wait(500)
        b.wait(60)
    assert not hosts.exists(), "a namespace was left behind"
    assert a.returncode == 0 and b.returncode == 0, ((logs / f"A{tag}.err").read_text()[-2000:], (logs / f"B{tag}.err").read_text()[-2000:])


def test_two_nodes_train_as_one_process_on_the_same_global_batch(take, light, tmp_path):
    one_process(take, light, tmp_path / "one", 3)
    two = tmp_path / "two"
    args = [take, "-o", two, *SMALL, "--config", light, "--stage1-steps", 3, "--stage2-steps", 0]
    two_nodes(args, 29411, tmp_path, "")
    assert json.loads((two / "train.json").read_text())["processes"] == 2
    l1, l2 = losses(tmp_path / "one"), losses(two)
    assert [s for s, _ in l2] == [1, 2, 3]
    assert max(abs(x - y) / max(abs(x), 1e-9) for (_, x), (_, y) in zip(l1, l2)) < TOLERANCE, (l1, l2)
    assert max_diff(weights(tmp_path / "one"), weights(two)) < TOLERANCE
    assert json.loads((two / "train.json").read_text())["elastic_run_id"] == "two-nodes"

    # the same command line again under the same rendezvous id, with a longer schedule: it goes on
    more = [take, "-o", two, *SMALL, "--config", light, "--stage1-steps", 5, "--stage2-steps", 0]
    two_nodes(more, 29412, tmp_path, "2")
    assert [s for s, _ in losses(two)] == [1, 2, 3, 4, 5]
