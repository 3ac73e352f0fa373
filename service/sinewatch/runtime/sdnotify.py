"""systemd's service notification protocol (``sd_notify(3)``), without libsystemd.

Under ``Type=notify`` systemd passes the path of a unix datagram socket in
``NOTIFY_SOCKET`` (a leading ``@`` names an abstract socket); the service sends
newline-separated ``KEY=VALUE`` assignments to it, one datagram per notification:

* ``READY=1`` once the daemon is subscribed and processing (systemd then considers the
  unit started, and ``systemctl start`` returns);
* ``WATCHDOG=1`` at least every ``WATCHDOG_USEC`` microseconds (``WatchdogSec=`` in the
  unit; systemd kills and restarts a service that misses it). The daemon sends it from a task
  on its event loop, so a stuck loop (an estimator that never returns, a blocking call) is
  caught, not just a dead process;
* ``STOPPING=1`` when it begins to drain, ``STATUS=...`` a line ``systemctl status`` shows.

``WATCHDOG_PID``, when set, names the process the watchdog applies to; another process
(a child that inherited the environment) must not send ``WATCHDOG=1``. Outside systemd
(no ``NOTIFY_SOCKET``) every call is a no-op. A failed send is logged once and never
raised: losing systemd must not stop estimation.
"""

from __future__ import annotations

import logging
import os
import socket
from collections.abc import Mapping

log = logging.getLogger("sinewatch.runtime.sdnotify")


class Notifier:
    """Sends notifications to ``NOTIFY_SOCKET`` (read once, from ``env``)."""

    def __init__(self, env: Mapping[str, str] | None = None) -> None:
        env = os.environ if env is None else env
        path = env.get("NOTIFY_SOCKET", "")
        self.address: str | None = None
        if path.startswith("@"):  # abstract namespace (Linux)
            self.address = "\0" + path[1:]
        elif path.startswith("/"):
            self.address = path
        self.watchdog_s: float | None = None
        usec = env.get("WATCHDOG_USEC", "")
        pid = env.get("WATCHDOG_PID", "")
        if self.address and usec.isdigit() and int(usec) > 0 and (not pid or pid == str(os.getpid())):
            self.watchdog_s = int(usec) / 1e6
        self._failed = False
        self.sent = 0

    @property
    def enabled(self) -> bool:
        return self.address is not None

    def notify(self, *assignments: str) -> bool:
        """Send ``KEY=VALUE`` lines as one datagram; True if it went out."""
        if self.address is None:
            return False
        data = "\n".join(assignments).encode()
        try:
            with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as sock:
                sock.sendto(data, self.address)
        except OSError as exc:
            if not self._failed:
                log.warning("sd_notify to %s failed (%s); further failures are not logged", self.address, exc)
                self._failed = True
            return False
        self.sent += 1
        return True

    def ready(self, status: str) -> bool:
        return self.notify("READY=1", f"STATUS={status}", f"MAINPID={os.getpid()}")

    def watchdog(self) -> bool:
        return self.watchdog_s is not None and self.notify("WATCHDOG=1")

    def stopping(self, status: str) -> bool:
        return self.notify("STOPPING=1", f"STATUS={status}")


__all__ = ["Notifier"]
