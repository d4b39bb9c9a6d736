"""The release: as pyproject.toml says (tests/test_config_cli.py); docs/protocol.md names what each release added."""

__version__ = "0.5.0"
