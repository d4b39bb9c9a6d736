"""What every silcr component shares: the wire protocol and its clients, option
declarations, environments, Zenoh sessions and the process lifecycle.

Nothing here imports a component (actor, buffer service, learner, deploy, bench):
they build on this, never the other way round (tests/test_layout.py checks it).
"""
