"""The learner: SAC/SILCR updates, weights for the actors, checkpoints and evaluation."""

import common  # noqa: F401  (sets the thread-pool defaults before numpy or torch is imported; see common/__init__.py)
