"""What runs the pipeline: the daemon (a Zenoh source), replay (an MCAP source), worker
processes, shards and their election, signals and systemd notification.
"""
