"""Where a torch network runs: the device, checked, and the CPU threads it may use.

Every torch baseline resolves ``--device`` through :func:`resolve_device`, so a device this
machine does not have is one clear error, and sets its CPU threads through
:func:`cpu_threads` (all the cores this process may run on, unless ``OMP_NUM_THREADS``
says otherwise). Importing this module does not import torch.
"""

from __future__ import annotations

import os
from typing import Any

from semantic3d.core.errors import Semantic3DError, require

__all__ = ["DeviceError", "cpu_threads", "resolve_device", "use_cpu_threads"]

DEVICES = ("cpu", "cuda")


class DeviceError(Semantic3DError, ValueError):
    """A torch device that this machine does not have (``cuda`` without a GPU)."""


def resolve_device(device: str) -> Any:
    """``torch.device(device)``, checked: ``cpu`` or ``cuda``, and ``cuda`` needs a CUDA GPU."""
    torch: Any = require("torch", "torch")
    try:
        resolved = torch.device(device)
    except RuntimeError as exc:
        raise DeviceError(f"device: expected cpu or cuda, found {device!r}") from exc
    if resolved.type not in DEVICES:
        raise DeviceError(f"device: expected cpu or cuda, found {device!r}")
    if resolved.type == "cuda" and not torch.cuda.is_available():
        raise DeviceError("device: cuda asked for, but torch sees no CUDA GPU on this machine")
    return resolved


def cpu_threads() -> int:
    """Threads a network should use on the CPU: ``OMP_NUM_THREADS`` when set to a positive
    integer, else every core this process may run on."""
    value = os.environ.get("OMP_NUM_THREADS", "").strip()
    if value.isdigit() and int(value) > 0:
        return int(value)
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def use_cpu_threads() -> int:
    """Let torch use :func:`cpu_threads` threads in this process; returns the count."""
    torch: Any = require("torch", "torch")
    threads = cpu_threads()
    if torch.get_num_threads() != threads:
        torch.set_num_threads(threads)
    return threads
