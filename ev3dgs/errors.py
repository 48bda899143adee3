"""Typed exceptions. The CLIs turn every Ev3dgsError into one line on stderr and exit code 2."""


class Ev3dgsError(Exception):
    """Base class of every error this package raises on purpose."""


class ConfigError(Ev3dgsError):
    """A config file or value is unknown, missing or impossible."""


class SchemaError(Ev3dgsError):
    """A scene file does not follow the schema; the message names the path inside the file."""


class InputError(Ev3dgsError):
    """Input arrays have the wrong shape, dtype or values (NaN, negative, unsorted...)."""


class Ev3dgsWarning(UserWarning):
    """Base class of every warning this package issues on purpose: the CLIs print it as one `warning:` line;
    other libraries' warnings are printed as such (cli/common.warning_text)."""


class SchemaWarning(Ev3dgsWarning):
    """A scene file follows the schema and can train, but something in it is odd; the message names the path."""


def raised_in_h5py(e: BaseException) -> bool:
    """True if `e` was raised inside h5py (its errors are OSError, KeyError, RuntimeError, ValueError... with
    HDF5's text): a damaged or unwritable file, not a bug of ours."""
    tb, last = e.__traceback__, None
    while tb is not None:
        last, tb = tb.tb_frame.f_code.co_filename, tb.tb_next
    return last is not None and "h5py" in last.replace("\\", "/").split("/")[:-1]
