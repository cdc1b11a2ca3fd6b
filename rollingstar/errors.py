"""Errors the command line turns into a one-paragraph message and exit code 2."""
from __future__ import annotations


class UserError(Exception):
    """Bad input from the user: a config, a recording, a path. The message says what and where."""


class ConfigError(UserError):
    """A config file that cannot be used: names the file, the key path and what was expected."""


class PipelineError(UserError):
    """A stage failed on a frame: names the stage, the frame and the cause."""
