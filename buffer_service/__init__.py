"""The buffer service: D_O, D_E, the rate limiter, mixed batches and checkpoints."""
