"""One root exception for sinewatch; every subclass also derives the builtin a caller
would expect (ValueError, TypeError), so generic handlers keep working.

Messages say what was expected and what was found.
"""

from __future__ import annotations


class SinewatchError(Exception):
    """Root of every error sinewatch raises on purpose."""


class ParameterError(SinewatchError, ValueError):
    """An estimator or configuration parameter is out of its valid range."""


class UnknownEstimatorError(SinewatchError, KeyError, ValueError):
    """No estimator is registered under the requested name."""

    def __str__(self) -> str:  # KeyError would repr() the message
        return str(self.args[0]) if self.args else ""


class InputError(SinewatchError, ValueError):
    """A block of samples was rejected before it reached an estimator.

    ``kind`` is the machine-readable reason used in ErrorReport messages.
    """

    kind = "invalid_input"

    def __init__(self, message: str, *, kind: str | None = None) -> None:
        super().__init__(message)
        if kind is not None:
            self.kind = kind


class InputTypeError(SinewatchError, TypeError):
    """A value of the wrong type was handed to an estimator or codec."""

    kind = "invalid_type"


class DecodeError(InputError):
    """A payload could not be decoded into a SampleBlock."""

    kind = "decode_error"


class UnsupportedVersionError(DecodeError):
    """The payload announces a wire-format version this build does not know."""

    kind = "unsupported_version"


class ConfigError(SinewatchError, ValueError):
    """The configuration file or environment is invalid."""


class OutputError(SinewatchError, OSError):
    """An output (a file, a directory) cannot be written where it was asked for."""

    def __str__(self) -> str:  # OSError would prefix an errno
        return str(self.args[0]) if self.args else ""


class ReplayMismatchError(SinewatchError, AssertionError):
    """A replay did not reproduce the recorded estimates bit for bit."""
