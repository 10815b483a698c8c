"""The torch device a command runs on: `--device cpu|cuda[:N]`, or the best one torch sees.

Every torch path of the product (training, evaluation, rendering, benchmarks, the GPU live runtime)
chooses its device here, so a wrong choice is one line and exit 2 wherever it is made."""
from __future__ import annotations

from typing import Optional

import torch

from inference.errors import InferenceError

CHOICES = ("cpu", "cuda")


def cuda_available() -> bool:
    return bool(torch.cuda.is_available())


def resolve_device(name: Optional[str], *, default: str = "auto") -> torch.device:
    """`name` None takes `default`: "auto" (CUDA when torch sees a GPU, else the CPU) or a device
    name. "cuda" without a GPU, an unknown kind or a GPU index that is not there: InferenceError."""
    text = (name if name is not None else default).strip().lower()
    if text == "auto":
        return torch.device("cuda", torch.cuda.current_device()) if cuda_available() else torch.device("cpu")
    kind, _, index = text.partition(":")
    if kind not in CHOICES or (index and not index.isdigit()) or (kind == "cpu" and index):
        raise InferenceError(f"--device: {name!r} is not a device (give cpu, cuda or cuda:N)")
    if kind == "cpu":
        return torch.device("cpu")
    if not cuda_available():
        built = torch.version.cuda
        why = f"this torch was built without CUDA (torch {torch.__version__})" if built is None else \
            f"torch {torch.__version__} (CUDA {built}) sees no GPU: check the driver (nvidia-smi)"
        raise InferenceError(f"--device {text}: no CUDA GPU here ({why}); give --device cpu")
    n = torch.cuda.device_count()
    i = int(index) if index else torch.cuda.current_device()
    if i >= n:
        raise InferenceError(f"--device {text}: there is no GPU {i} (torch sees {n})")
    return torch.device("cuda", i)


def describe(device: torch.device) -> dict:
    """What /status and --json say of a device: its kind and, for a GPU, its name and memory."""
    out = {"device": str(device)}
    if device.type == "cuda":
        props = torch.cuda.get_device_properties(device)
        out.update(gpu=props.name, memory_gib=round(props.total_memory / 2**30, 1), torch=torch.__version__, cuda=torch.version.cuda)
    return out


def synchronize(device: torch.device) -> None:
    """Wait for the device's queued work (for timing: CUDA runs asynchronously)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)
