"""The buffer service: D_O, D_E, the rate limiter, mixed batches and checkpoints."""

import common  # noqa: F401  (sets the thread-pool defaults before numpy or torch is imported; see common/__init__.py)
