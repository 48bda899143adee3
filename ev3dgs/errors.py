"""Typed exceptions. The CLIs turn every Ev3dgsError into one line on stderr and exit code 2."""


class Ev3dgsError(Exception):
    """Base class of every error this package raises on purpose."""


class ConfigError(Ev3dgsError):
    """A config file or value is unknown, missing or impossible."""


class SchemaError(Ev3dgsError):
    """A scene file does not follow the schema; the message names the path inside the file."""


class InputError(Ev3dgsError):
    """Input arrays have the wrong shape, dtype or values (NaN, negative, unsorted...)."""


class SchemaWarning(UserWarning):
    """A scene file follows the schema and can train, but something in it is odd; the message names the path."""
