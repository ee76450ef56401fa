"""Which array backend and device the particle maps run on (``slam.backend``, ``slam.device``).

No torch import at module level: torch is the optional ``learn`` extra, asked for only when the
torch backend is selected.
"""

from __future__ import annotations

from typing import Literal

from core.errors import UserError

Backend = Literal["numpy", "torch"]
Device = Literal["auto", "cpu", "cuda"]


def resolve_device(backend: Backend, device: Device) -> tuple[str, str]:
    """The device the filter runs on and a note for the log (empty unless ``auto`` fell back).

    ``numpy`` runs on the CPU (``device = cuda`` with it is an error). ``torch``: ``cuda`` needs a CUDA
    device; ``auto`` takes one when torch sees it and otherwise falls back to the CPU.
    """
    if backend == "numpy":
        if device == "cuda":
            raise UserError("slam.device = cuda needs slam.backend = torch (the numpy backend runs on the CPU)")
        return "cpu", ""
    if backend != "torch":
        raise UserError(f"unknown slam.backend {backend!r}; use numpy or torch")
    try:
        import torch
    except ImportError as exc:
        raise UserError("slam.backend = torch needs PyTorch (the `learn` extra: pip install -e '.[learn]'); "
                        f"or set slam.backend = numpy ({exc})") from exc
    has_cuda = bool(torch.cuda.is_available())
    if device == "cuda" and not has_cuda:
        raise UserError(f"slam.device = cuda but torch {torch.__version__} sees no CUDA device; "
                        "use slam.device = auto or cpu")
    if device == "auto":
        if has_cuda:
            return "cuda", ""
        return "cpu", "slam.device = auto: torch sees no CUDA device, running the torch backend on the CPU"
    if device not in ("cpu", "cuda"):
        raise UserError(f"unknown slam.device {device!r}; use auto, cpu or cuda")
    return device, ""
