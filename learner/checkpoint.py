"""Atomic checkpoints: write a temporary file in the same directory, fsync, rename.

A crash at any moment leaves either the previous checkpoint or the new one,
never a half-written file.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from silcr.common.atomic_file import write_atomic


class CheckpointError(RuntimeError):
    pass


def save_checkpoint(path: Path, payload: dict[str, Any]) -> None:
    write_atomic(path, lambda f: torch.save(payload, f))


def load_checkpoint(path: Path) -> dict[str, Any]:
    if not path.exists():
        raise CheckpointError(f"no checkpoint at {path}")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as e:  # torch raises several types for truncated or foreign files
        raise CheckpointError(f"checkpoint {path} is unreadable or corrupt ({type(e).__name__}: {e})") from None
    if not isinstance(payload, dict) or "sac" not in payload or "counters" not in payload:
        raise CheckpointError(f"{path} is not a silcr learner checkpoint")
    return payload
