"""The applications: the command line and what it runs (demo, bench, replay, export, compare,
plot, feed, console, the sampled-values gateway). The top layer: nothing below imports it.
"""
