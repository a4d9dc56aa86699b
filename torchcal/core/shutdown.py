"""A faster interpreter exit for processes that imported torch, scikit-learn and the rest.

Two ways, by how a process ends. The ``torchcal`` command ends by :func:`end_process`: what a
normal exit does that matters, then ``os._exit`` (the interpreter's teardown of the torch modules
took 0.5-0.9 s). A process that ends through the interpreter's normal exit (a study's local
worker, ended by multiprocessing) calls :func:`skip_collection_at_exit`.

At exit CPython runs its cyclic garbage collector over every object still alive: with torch
imported that is most of a second of CPU (0.8-1.1 s for a process that imported torch, against
0.2-0.3 s with the collector frozen, on the project's 2-core machine). Freezing the collector at
exit skips that pass. Used where a process ends through the interpreter's normal exit, as a
study's local worker processes do (the ``torchcal`` command itself ends by ``os._exit``,
:func:`torchcal.cli.console_main`). Nothing the process wrote depends on the pass: outputs are
written atomically and closed when they are written, ``atexit`` handlers (registered before or
after) still run, objects freed by reference counting are still freed, and Python never promised
to finalise objects still alive at exit.
"""

from __future__ import annotations

import atexit
import contextlib
import gc
import os
import sys
import threading
from typing import NoReturn

_registered = False


def skip_collection_at_exit() -> None:
    """Freeze the garbage collector when the interpreter exits (once per process; idempotent).

    The process works on as before until it exits: the freeze happens only then.
    """
    global _registered
    if not _registered:
        _registered = True
        atexit.register(gc.freeze)


def end_process(status: int) -> NoReturn:
    """End this process with ``status`` without tearing down its modules.

    First what a normal exit does that matters, in its order: thread pools' exit hooks, non-daemon
    threads joined, ``atexit`` handlers; then the standard streams are flushed. A process stopped by
    Ctrl-C or SIGTERM (130, 143) ends at once: it waits for no thread.
    """
    if status not in (130, 143):
        # what the interpreter runs first at exit: thread pools' exit hooks, then joins non-daemon threads
        shutdown = getattr(threading, "_shutdown", None)
        if shutdown is not None:
            shutdown()
        for thread in threading.enumerate():
            if thread is not threading.current_thread() and not thread.daemon:
                thread.join()
        atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):  # a reader that went away, a stream closed by a handler
            stream.flush()
    os._exit(status)
