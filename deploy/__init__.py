"""Running silcr: the local launcher, sweeps, monitoring and deployment files."""

import common  # noqa: F401  (sets the thread-pool defaults before numpy or torch is imported; see common/__init__.py)
