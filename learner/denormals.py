"""Denormal floats flushed to zero while the learner's update runs on a CPU.

Adam keeps running averages of each gradient and of its square. A weight whose
gradient is zero for a while (a ReLU unit that went quiet, which is common in
SAC's networks) sees its averages decay by 0.9 and 0.999 per step until they
fall below float32's smallest normal number, 1.2e-38, and stay in the
denormal range for hundreds to thousands of steps. x86 CPUs compute on
denormals through a microcode assist, tens of times slower than on normal
numbers. Measured on this project's 2-core machine (docs/performance.md,
"Against Stable-Baselines3"), from a Hopper-v5 learner after 10,000 updates:
7% of the critics' Adam state and 17% of the actor's were denormal, and one
critic Adam step took 1.08 ms instead of 0.15 ms with them flushed: a fifth of
the whole update.

Flushing changes nothing an update can see: a denormal moment contributes
lr * m / (sqrt(v) + eps) < 1e-30 to a weight, far below the weight's last bit.

The CPU's mode (MXCSR's flush-to-zero and denormals-are-zero bits) belongs to
each thread. So the mode is set only around the update, not for the process:
in `silcr train --single-process` the same thread steps MuJoCo, whose physics
must not change with the learner's settings. torch's OpenMP threads flush too
while it is set (checked: a 2-thread multiply of 2M denormals gave zeros,
whether the thread pool started before the block or inside it).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch


@contextlib.contextmanager
def flushed(device: torch.device, enabled: bool = True) -> Iterator[None]:
    """Run the block with denormals flushed to zero on this thread (CPU only; a no-op elsewhere or if not `enabled`).

    The previous mode cannot be read back through torch, so on exit it is set to
    off, the default; blocks of this kind are not nested.
    """
    if not enabled or device.type != "cpu" or not torch.set_flush_denormal(True):
        yield
        return
    try:
        yield
    finally:
        torch.set_flush_denormal(False)
