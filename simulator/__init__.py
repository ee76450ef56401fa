"""ColoRadar-format log simulator (placeholder until the simulator lands)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pipeline.errors import UserError


def generate_sequence(seq: Any) -> Path:
    raise UserError(f"sequence '{seq.name}': the simulator is not implemented yet")


def simulate_to(**kwargs: Any) -> Path:
    raise UserError("the simulator is not implemented yet")
