"""What runs the pipeline: the daemon (a Zenoh source), replay (an MCAP source), worker
processes, shards and their election, signals and systemd notification.
"""

import sinewatch.host_arithmetic  # noqa: F401  # first, before numpy loads (its docstring says why)

# isort: split
