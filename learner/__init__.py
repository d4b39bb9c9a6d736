"""The learner: SAC/SILCR updates, weights for the actors, checkpoints and evaluation."""
