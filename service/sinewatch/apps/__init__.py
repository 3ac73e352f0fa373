"""The applications: the command line and what it runs (demo, bench, replay, export, compare,
plot, feed, console, the sampled-values gateway). The top layer: nothing below imports it.
"""

import sinewatch.host_arithmetic  # noqa: F401  # first, before numpy loads (its docstring says why)

# isort: split
