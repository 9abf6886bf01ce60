"""The runner's error types."""
from __future__ import annotations


class ConfigError(ValueError):
    """A bad run setting (a value, a name, a combination): the command line prints it as one line
    and exits with status 2. Any other exception is a failure and keeps its traceback."""

