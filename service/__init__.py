"""sinewatch: streaming estimation of sinusoid parameters over Eclipse Zenoh.

The package is laid out over the repository's top-level folders: ``service/`` is
``sinewatch`` itself (daemon, pipeline, recorder, replay, estimators, CLI),
``clients/`` is ``sinewatch.clients`` and ``schemas/`` is ``sinewatch.schemas``.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("sinewatch")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0.0.0"
