"""The training process group under torchrun's agent store (inference/train/run.py _init_group): the
workers of one attempt find each other although their agents count restarts differently (one node's
worker died and its agent counts a restart; the other agent restarted its workers for the waiting
node and does not), and although the agent store still holds an earlier attempt's entry."""
from __future__ import annotations

import datetime
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch.distributed as dist

from inference.train.run import GROUP_STORE_KEY

REPO = Path(__file__).resolve().parents[2]
WORKER = """
import sys, torch, torch.distributed as dist
from inference.train.run import _init_group
_init_group(dist, "gloo")
t = torch.tensor([float(dist.get_rank() + 1)])
dist.all_reduce(t)
print(int(t.item()))
dist.destroy_process_group()
"""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.timeout(120)
def test_workers_whose_agents_count_restarts_differently_still_form_one_group():
    agent = dist.TCPStore("127.0.0.1", 0, 2, is_master=True, timeout=datetime.timedelta(seconds=60), wait_for_workers=False)
    # an earlier attempt's entry: its rank 0 is gone, its port refuses
    agent.set(GROUP_STORE_KEY, f"{free_port()} 0123456789abcdef")
    procs = []
    # rank 1 first: it reads the earlier attempt's entry and must not take it; rank 0 comes 4 s later
    for rank, restarts in ((1, "1"), (0, "0")):
        env = {k: v for k, v in os.environ.items() if k not in ("GLOO_SOCKET_IFNAME",)} | {
            "RANK": str(rank), "WORLD_SIZE": "2", "LOCAL_RANK": "0", "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(agent.port),
            "TORCHELASTIC_USE_AGENT_STORE": "True", "TORCHELASTIC_RESTART_COUNT": restarts, "OMP_NUM_THREADS": "1"}
        procs.append(subprocess.Popen([sys.executable, "-c", WORKER], cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
        time.sleep(4.0 if rank == 1 else 0.0)
    results = []
    for p in procs:
        try:
            out, err = p.communicate(timeout=90)
        except subprocess.TimeoutExpired:
            for q in procs:
                q.kill()
            pytest.fail("the two workers did not form a group within 90 s")
        results.append((p.returncode, out.strip(), err[-1500:]))
    assert [(code, out) for code, out, _ in results] == [(0, "3"), (0, "3")], results
