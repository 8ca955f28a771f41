"""The last resort behind Ctrl-C and SIGTERM: a command stuck inside one long native computation.

Python runs a signal's handler in the main thread between two bytecodes. A main thread inside one
long call into native code (a LAPACK factorisation, a huge torch kernel, a C library reading a
file) does not get there: Ctrl-C is noted and ignored until the call returns, which may be
minutes. :class:`InterruptWatchdog` watches for that case from a second thread:

- the C-level handler writes every signal's number to a pipe (``signal.set_wakeup_fd``), also
  while the main thread is busy; the watchdog thread reads it;
- a Python-level handler that ran (the main thread was responsive) calls :meth:`acknowledge`;
- a SIGINT or SIGTERM not acknowledged within ``grace_s`` calls ``on_stuck(signum)`` from the
  watchdog thread (which writes the run folder's status) and ends the process with exit code
  128 + signum, the code a process killed by the signal reports to its shell.

Forked children (a DataLoader's workers) stop writing to the parent's pipe (``os.register_at_fork``).
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from typing import Callable, Optional

#: seconds the main thread has to run a signal's handler before the watchdog ends the process
GRACE_S = 1.5

_WATCHED = (signal.SIGINT, signal.SIGTERM)
#: a handler run this long before its signal's byte was read still answers it, s
_SAME_BURST_S = 0.5


def _forget_wakeup_fd_in_child() -> None:
    try:
        signal.set_wakeup_fd(-1)
    except (ValueError, OSError):  # not the main thread of the child: nothing was inherited to undo
        pass


os.register_at_fork(after_in_child=_forget_wakeup_fd_in_child)


class InterruptWatchdog:
    """Context manager (main thread only; elsewhere it does nothing).

    Args:
        on_stuck: called with the signal number from the watchdog thread when the main thread did
            not handle a SIGINT / SIGTERM within ``grace_s``; it must be quick and must not raise
            (exceptions are swallowed). Then the process exits with 128 + signum.
        grace_s: seconds (> 0).
    """

    def __init__(self, on_stuck: Callable[[int], None], grace_s: float = GRACE_S):
        if not grace_s > 0:
            raise ValueError(f"grace_s must be > 0, got {grace_s}")
        self.on_stuck, self.grace_s = on_stuck, float(grace_s)
        self._cond = threading.Condition()
        self._handled_at = -float("inf")  # time.monotonic() of the last handler that ran
        self._active = False
        self._old_fd: Optional[int] = None

    def acknowledge(self) -> None:
        """Say that a Python-level handler ran (call it first thing in the handler)."""
        with self._cond:
            self._handled_at = time.monotonic()
            self._cond.notify_all()

    def __enter__(self) -> "InterruptWatchdog":
        if threading.current_thread() is not threading.main_thread():
            return self
        self._r, self._w = os.pipe()
        os.set_blocking(self._w, False)
        try:
            self._old_fd = signal.set_wakeup_fd(self._w, warn_on_full_buffer=False)
        except (ValueError, OSError):  # an embedded interpreter: no watchdog
            os.close(self._r)
            os.close(self._w)
            return self
        self._active = True
        self._thread = threading.Thread(target=self._watch, name="dvsland-interrupt-watchdog", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        if self._active:
            self._active = False
            signal.set_wakeup_fd(self._old_fd if self._old_fd is not None else -1)
            os.close(self._w)  # the watchdog's read returns b"": it ends
            self._thread.join(timeout=1.0)
            os.close(self._r)
        return False

    def _watch(self) -> None:
        while True:
            try:
                data = os.read(self._r, 64)
            except OSError:
                return
            if not data:
                return
            for signum in data:
                if signum in _WATCHED:
                    self._await_handler(signum)

    def _await_handler(self, signum: int) -> None:
        # a handler that ran shortly before the byte was read counts (the handler can be first; two
        # quick signals give two bytes but may run the handler once)
        since = time.monotonic() - _SAME_BURST_S
        with self._cond:
            handled = self._cond.wait_for(lambda: self._handled_at >= since or not self._active, timeout=self.grace_s)
        if handled or not self._active:
            return
        try:
            self.on_stuck(signum)
        except BaseException:  # noqa: BLE001 - the process ends either way
            pass
        sys.stderr.flush()
        os._exit(128 + signum)


__all__ = ["GRACE_S", "InterruptWatchdog"]
