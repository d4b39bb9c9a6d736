"""The benchmark suite behind silcr bench."""

import common  # noqa: F401  (sets the thread-pool defaults before numpy or torch is imported; see common/__init__.py)
