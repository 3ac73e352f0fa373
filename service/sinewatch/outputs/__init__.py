"""Where estimates go: the MCAP recorder, the Zenoh publisher, the Foxglove live view,
Prometheus metrics, the C37.118.2 server, the per-sample track.
"""

import sinewatch.host_arithmetic  # noqa: F401  # first, before numpy loads (its docstring says why)

# isort: split
