"""Checkpoints of the completion network: safetensors (preferred) or ``torch.save`` files.

A checkpoint holds the weights and plain metadata: the model config, the normalisation scale (metres per
unit of patch coordinates) and a training record. ``.safetensors`` files carry the metadata as JSON
strings in their header; ``.pt`` files are a dict ``{"state_dict", "meta_json"}`` read back with
``torch.load(weights_only=True)``. Neither format unpickles arbitrary objects.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from core.errors import UserError
from stages.complete.model import ModelConfig, UpPoinTr

FORMAT = "radar-pipeline/complete"
FORMAT_VERSION = "1"


@dataclass
class CheckpointMeta:
    """What a checkpoint says about itself besides the weights."""

    config: ModelConfig
    norm_scale: float
    train: dict[str, Any] = field(default_factory=dict)

    def to_strings(self) -> dict[str, str]:
        return {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "model_config": json.dumps(self.config.to_dict()),
            "norm_scale": repr(float(self.norm_scale)),
            "train": json.dumps(self.train),
        }

    @classmethod
    def from_strings(cls, d: dict[str, str], where: str) -> CheckpointMeta:
        if d.get("format") != FORMAT:
            raise UserError(f"{where}: not a completion-network checkpoint (format {d.get('format')!r})")
        if d.get("format_version") != FORMAT_VERSION:
            raise UserError(f"{where}: checkpoint format version {d.get('format_version')} is not "
                            f"{FORMAT_VERSION}; retrain it with `pipeline train`")
        return cls(ModelConfig.from_dict(json.loads(d["model_config"])), float(d["norm_scale"]),
                   json.loads(d.get("train", "{}")))


def save_checkpoint(path: str | Path, model: UpPoinTr, meta: CheckpointMeta, half: bool = False) -> Path:
    """Write ``model``'s weights and ``meta``; ``half`` stores float16 (restored to float32 on load)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    if half:
        state = {k: v.half() if v.is_floating_point() else v for k, v in state.items()}
    tmp = path.with_name(f".{path.name}.tmp")
    if path.suffix == ".safetensors":
        from safetensors.torch import save_file

        save_file(state, str(tmp), metadata=meta.to_strings())
    elif path.suffix in (".pt", ".pth"):
        torch.save({"state_dict": state, "meta_json": json.dumps(meta.to_strings())}, tmp)
    else:
        raise UserError(f"{path}: checkpoint must end in .safetensors or .pt")
    tmp.chmod(0o644)
    tmp.replace(path)
    return path


def load_checkpoint(path: str | Path, device: str | torch.device = "cpu") -> tuple[UpPoinTr, CheckpointMeta]:
    """The model (in eval mode, float32, on ``device``) and its metadata."""
    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: checkpoint not found; train one with `pipeline train` or set complete.checkpoint")
    if path.suffix == ".safetensors":
        from safetensors import safe_open
        from safetensors.torch import load_file

        with safe_open(str(path), framework="pt") as f:
            strings = f.metadata() or {}
        state = load_file(str(path))
    elif path.suffix in (".pt", ".pth"):
        blob = torch.load(path, map_location="cpu", weights_only=True)
        if not isinstance(blob, dict) or "state_dict" not in blob or "meta_json" not in blob:
            raise UserError(f"{path}: not a completion-network checkpoint (expected state_dict and meta_json)")
        state, strings = blob["state_dict"], json.loads(blob["meta_json"])
    else:
        raise UserError(f"{path}: checkpoint must end in .safetensors or .pt")
    meta = CheckpointMeta.from_strings(strings, str(path))
    model = UpPoinTr(meta.config)
    state = {k: v.float() if v.is_floating_point() else v for k, v in state.items()}
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        first = str(exc).splitlines()[0]
        raise UserError(f"{path}: weights do not match the model config it declares ({first})") from exc
    return model.to(device).eval(), meta

