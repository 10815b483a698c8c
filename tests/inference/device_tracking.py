"""A CPU stand-in for "does every tensor follow the model's device?" (test helper).

On a CPU-only machine every tensor is on the CPU, so a tensor that stays behind when the model moves
to a GPU (a `torch.tensor(...)`, `torch.from_numpy(...)` or `torch.zeros(...)` made without
`device=`, or a `.cpu()` result fed back into the model's arithmetic) goes unnoticed until the run
reaches a GPU and dies with "Expected all tensors to be on the same device". `DeviceTracker` is a
TorchFunctionMode that gives every tensor a shadow placement while code runs:

- "device": the model's parameters and buffers (`mark_device`), anything moved with
  `.to(<device>)` / `.cuda()`, and whatever an operation on a "device" tensor returns
  (`zeros_like`, `new_zeros`, arithmetic, ...);
- "any": made with an explicit `device=` (taken to name the device of the data it joins): it
  takes the placement of what it meets;
- "host": factories without `device=` (`torch.tensor`, `zeros`, `arange`, `eye`, ...), tensors the
  mode never saw made (`torch.from_numpy`, which torch does not route through modes), `.cpu()`.

An operation that mixes a "device" tensor with a "host" tensor of one or more dimensions is what a
GPU refuses (CUDA accepts 0-dim CPU tensors as scalars, and CPU index tensors in `x[index]`): the
tracker records it with the first line of our code on the stack.
"""
from __future__ import annotations

import sys
from pathlib import Path

import torch
from torch.overrides import TorchFunctionMode
from torch.utils._pytree import tree_flatten

REPO = Path(__file__).resolve().parents[2]
OURS = tuple(str(REPO / p) for p in ("inference", "rig", "benchmarks", "simulator", "calibration", "tests"))
HERE = str(Path(__file__).resolve())
_ATTR = "_rig_placement"
DEVICE, HOST, ANY = "device", "host", "any"
# Operations whose result lives wherever their argument says (explicit device transfers).
_MOVES = {"to", "cuda"}
_INDEXING = {"__getitem__"}
# Copies between devices are what these are for.
_CROSSING = {"copy_", "__set__"}


def _place(t: torch.Tensor) -> str:
    # Parameters move with their module (Module.to swaps their data, keeping the Python object).
    return DEVICE if isinstance(t, torch.nn.Parameter) else getattr(t, _ATTR, HOST)


def _tag(out, where: str) -> None:
    for t in tree_flatten(out)[0]:
        if isinstance(t, torch.Tensor):
            try:
                setattr(t, _ATTR, where)
            except (AttributeError, RuntimeError):  # a tensor type that takes no attributes
                pass


def _explicit_device(args, kwargs) -> bool:
    if kwargs.get("device") is not None:
        return True
    return any(isinstance(a, (torch.device, str)) and not isinstance(a, torch.dtype) and _is_device(a) for a in args)


def _is_device(a) -> bool:
    if isinstance(a, torch.device):
        return True
    try:
        torch.device(a)
        return True
    except (RuntimeError, TypeError):
        return False


def _caller() -> str:
    f = sys._getframe(2)
    while f is not None:
        name = f.f_code.co_filename
        if name.startswith(OURS) and name != HERE:
            return f"{Path(name).relative_to(REPO)}:{f.f_lineno} ({f.f_code.co_name})"
        f = f.f_back
    return "(outside our code)"


class DeviceTracker(TorchFunctionMode):
    def __init__(self):
        super().__init__()
        self.mixed: dict[str, str] = {}  # where -> the operation

    def mark_device(self, module: torch.nn.Module) -> None:
        for t in list(module.parameters()) + list(module.buffers()):
            setattr(t, _ATTR, DEVICE)

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        out = func(*args, **kwargs)
        name = getattr(func, "__name__", str(func))
        tensors = [t for t in tree_flatten((args, kwargs))[0] if isinstance(t, torch.Tensor)]
        if name in _MOVES:
            if name == "to" and not _explicit_device(args[1:], kwargs) and not any(
                    isinstance(a, torch.Tensor) for a in args[1:]):
                _tag(out, _place(args[0]))  # .to(dtype): stays where it was
            elif name == "to" and any(isinstance(a, torch.Tensor) for a in args[1:]):
                _tag(out, _place(next(a for a in args[1:] if isinstance(a, torch.Tensor))))
            else:
                _tag(out, DEVICE)
            return out
        if name == "cpu":
            _tag(out, HOST)
            return out
        if not tensors:
            _tag(out, ANY if _explicit_device((), kwargs) else HOST)
            return out
        on_device = [t for t in tensors if _place(t) == DEVICE]
        if on_device and name in _CROSSING:
            return out
        if on_device:
            checked = tensors if name not in _INDEXING else tensors[:1]
            stray = [t for t in checked if _place(t) == HOST and t.dim() > 0]
            if stray:
                where = _caller()
                self.mixed.setdefault(where, f"{name}: {len(on_device)} device tensor(s) with host tensor(s) of shape "
                                             f"{', '.join(str(tuple(t.shape)) for t in stray[:3])}")
            _tag(out, DEVICE)
        else:
            _tag(out, HOST if any(_place(t) == HOST for t in tensors) else ANY)
        return out

    def report(self) -> str:
        return "\n".join(f"{where}: {what}" for where, what in sorted(self.mixed.items()))
