"""Actors: roll out episodes and publish them to the buffer service."""
