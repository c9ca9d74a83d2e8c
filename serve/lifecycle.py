"""The serving process's life around uvicorn: noticing that shutdown has begun, and that the parent has died.

- :func:`shutdown_signals`: while the app runs, SIGTERM and SIGINT call a function on the event loop (the drain of
  the uploads, :meth:`occflownet.serve.limits.Uploads.drain`) and then go on to the handler that was installed
  before (uvicorn's, which starts its graceful shutdown). uvicorn installs its handlers before the app's lifespan
  starts and puts back the ones it found when it stops; only the main thread can set handlers, so an app served
  from another thread (tests) keeps uvicorn's alone.
- :func:`watch_parent`: in a worker of ``occflownet serve --workers N``, a daemon thread that sends the process
  SIGTERM when its parent (uvicorn's supervisor) has gone — killed with SIGKILL, it cannot stop its workers itself —
  so the workers shut down as on any SIGTERM instead of serving on.
"""
from __future__ import annotations

import logging
import multiprocessing
import os
import signal
import threading
from contextlib import contextmanager

log = logging.getLogger("occflownet.serve")

SHUTDOWN_SIGNALS = (signal.SIGTERM, signal.SIGINT)
PARENT_POLL_S = 0.5


@contextmanager
def shutdown_signals(loop, on_signal):
    """While the block runs, SIGTERM/SIGINT first schedule ``on_signal()`` on ``loop``, then do what the handler
    installed before does (call it; the default action: raise the signal again without ours; ignored: nothing); the
    earlier handlers are back afterwards. Nothing in other threads."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {sig: signal.getsignal(sig) for sig in SHUTDOWN_SIGNALS}

    def handler(sig, frame):
        loop.call_soon_threadsafe(on_signal)
        if callable(previous[sig]):
            previous[sig](sig, frame)
        elif previous[sig] == signal.SIG_DFL:
            signal.signal(sig, signal.SIG_DFL)
            signal.raise_signal(sig)

    for sig in SHUTDOWN_SIGNALS:
        signal.signal(sig, handler)
    try:
        yield
    finally:
        for sig, old in previous.items():
            if signal.getsignal(sig) is handler:
                signal.signal(sig, old)


def watch_parent(poll_s: float = PARENT_POLL_S) -> threading.Event:
    """Start the parent watch of this process (module docstring) → an Event that stops it when set. The parent is
    the process that started this one (multiprocessing's record of it in a spawned worker), so a parent that died
    before the watch began is noticed too."""
    stop = threading.Event()
    started_by = multiprocessing.parent_process()
    parent = started_by.pid if started_by is not None else os.getppid()

    def watch():
        while not stop.wait(poll_s):
            if os.getppid() != parent:
                log.warning("parent process %d has gone: this worker (pid %d) shuts down", parent, os.getpid())
                os.kill(os.getpid(), signal.SIGTERM)
                return

    threading.Thread(target=watch, name="occflownet-parent-watch", daemon=True).start()
    return stop
