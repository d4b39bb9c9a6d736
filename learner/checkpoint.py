"""Learner checkpoints: written atomically, read without running code.

Writing: a temporary file in the same directory, fsync, rename, so a crash at any
moment leaves either the previous checkpoint or the new one, never a half-written file.

Reading: `torch.load(weights_only=True)`, which unpickles only tensors and plain
containers and numbers. A checkpoint is a pickle, and a full unpickler runs
whatever code the file names, so `silcr eval` on a file from elsewhere must not
use one. Every checkpoint silcr has written holds only such data and loads the same way.
"""

from __future__ import annotations

import pickle
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
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as e:  # what weights_only refuses: objects that are not plain data
        # torch's message suggests loading with weights_only=False; keep only the line naming the object.
        what = next((line.strip() for line in str(e).splitlines() if "GLOBAL" in line), type(e).__name__)
        raise CheckpointError(f"checkpoint {path} holds objects other than tensors and plain data, which could run "
                              f"code when loaded; refused ({what})") from None
    except Exception as e:  # torch raises several types for truncated or foreign files
        raise CheckpointError(f"checkpoint {path} is unreadable or corrupt ({type(e).__name__}: {e})") from None
    if not isinstance(payload, dict) or not isinstance(payload.get("sac"), dict) or "counters" not in payload:
        raise CheckpointError(f"{path} is not a silcr learner checkpoint")
    return payload
