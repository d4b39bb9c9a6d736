"""Actors: roll out episodes and publish them to the buffer service."""

import common  # noqa: F401  (sets the thread-pool defaults before numpy or torch is imported; see common/__init__.py)
