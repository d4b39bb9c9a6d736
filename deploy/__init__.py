"""Running silcr: the local launcher, sweeps, monitoring and deployment files."""
