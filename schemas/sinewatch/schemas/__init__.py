"""The bottom layer of sinewatch: wire format (messages, codec) and configuration.

numpy and pydantic only: no Zenoh, no MCAP, no estimator (and so no numba) is imported
here, so a gateway, a client or ``sinewatch config show`` can load it in milliseconds.
"""

from importlib.metadata import PackageNotFoundError, version

from sinewatch.schemas.messages import (
    ESTIMATE_FORMAT_VERSION,
    FORMAT_VERSION,
    MESSAGE_MODELS,
    ErrorKind,
    ErrorReport,
    Estimate,
    Fencing,
    SampleBlock,
    Status,
)

try:
    __version__ = version("sinewatch")
except PackageNotFoundError:  # a source tree that was never installed
    __version__ = "0.0.0"

__all__ = [
    "ESTIMATE_FORMAT_VERSION",
    "FORMAT_VERSION",
    "MESSAGE_MODELS",
    "ErrorKind",
    "ErrorReport",
    "Estimate",
    "Fencing",
    "SampleBlock",
    "Status",
    "__version__",
]
