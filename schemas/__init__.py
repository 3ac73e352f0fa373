"""Wire format (messages, codec) and configuration models of sinewatch."""

from sinewatch.schemas.messages import (
    FORMAT_VERSION,
    MESSAGE_MODELS,
    ErrorKind,
    ErrorReport,
    Estimate,
    SampleBlock,
    Status,
)

__all__ = [
    "FORMAT_VERSION",
    "MESSAGE_MODELS",
    "ErrorKind",
    "ErrorReport",
    "Estimate",
    "SampleBlock",
    "Status",
]
