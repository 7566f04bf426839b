"""Where the learned model evaluates: CPU (the default) or a CUDA device.

``resolve_device`` turns ``cpu``, ``cuda``, ``cuda:N`` or ``auto`` (cuda when torch sees a GPU)
into a torch device, refusing one torch cannot use; ``using_device`` sets the device learned
models are loaded to when none is given (what the commands' ``--device`` does, so that a plan
loads ``--model learned`` there without the planner knowing); ``GPU_MIN_BATCH`` is the batch
size from which a model on a GPU evaluates there (smaller batches stay on the CPU paths).
"""

from __future__ import annotations

import contextvars

import torch

#: A model on a GPU evaluates batches of at least this many configurations there; smaller ones
#: on the CPU paths (a GPU call's fixed latency, ~0.3 ms with its transfers on an H100, exceeds
#: the CPU's time for them: benchmarks/results/learned_gpu_h100.json).
GPU_MIN_BATCH = 1024
#: device of models loaded without one (:class:`using_device`): context state (per thread and
#: task, restored on exit), not a cache
_default_device: contextvars.ContextVar[str] = contextvars.ContextVar("ctrplan_device", default="cpu")


def resolve_device(device: str | torch.device | None = "cpu") -> torch.device:
    """A torch device from ``cpu``, ``cuda``, ``cuda:N``, ``auto`` (cuda when torch sees a GPU,
    else cpu) or None (cpu). ValueError when torch cannot use it (no CUDA, a bad name)."""
    if device is None:
        return torch.device("cpu")
    if isinstance(device, torch.device):
        dev = device
    else:
        text = str(device).strip().lower()
        if text == "auto":
            return torch.device("cuda" if torch.cuda.is_available() else "cpu")
        try:
            dev = torch.device(text)
        except (RuntimeError, ValueError):
            raise ValueError(f"{str(device)[:40]!r} is not a device (cpu, cuda, cuda:N or auto)") from None
    if dev.type == "cpu":
        return dev
    try:
        torch.empty(1, device=dev)
    except Exception as exc:     # no CUDA build, no GPU, an index past the last GPU
        raise ValueError(f"{str(device)[:40]!r} is not available ({exc.__class__.__name__}: "
                         f"torch sees {torch.cuda.device_count()} CUDA device(s))") from None
    return dev


class using_device:
    """Context manager: learned models loaded inside it without a ``device`` (``--model
    learned`` or a model file, through :func:`ctrplan.shape.models.load_model`) go to
    ``device`` (:func:`resolve_device`: ``cpu``, ``cuda[:N]``, ``auto``). What the commands'
    ``--device`` sets."""

    def __init__(self, device: str | torch.device | None):
        self.device = str(resolve_device(device))
        self._tokens: list[contextvars.Token] = []

    def __enter__(self) -> str:
        self._tokens.append(_default_device.set(self.device))
        return self.device

    def __exit__(self, *exc) -> None:
        _default_device.reset(self._tokens.pop())


def current_device() -> str:
    """The device learned models are loaded to when none is given (``cpu`` unless inside
    :class:`using_device`)."""
    return _default_device.get()
