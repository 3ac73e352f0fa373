"""The pipeline: channel -> estimator -> sinks, the continuity of each channel's stream,
windows of a recording, the COMTRADE reader. It knows no transport and no output format.
"""

import sinewatch.host_arithmetic  # noqa: F401  # first, before numpy loads (its docstring says why)

# isort: split
