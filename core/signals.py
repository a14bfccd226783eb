"""Python's signal handlers kept across the import of native libraries that install their own.

pycolmap (through glog) installs crash handlers on import, SIGTERM among them: a terminated
run would print a native stack dump instead of unwinding through Python (which removes
temporaries and stops pool workers).
"""

from __future__ import annotations

import contextlib
import signal
import threading
from typing import Iterator

#: Signals a library may take over that Python code here handles itself.
KEPT = (signal.SIGTERM, signal.SIGINT)


@contextlib.contextmanager
def python_signal_handlers() -> Iterator[None]:
    """Put back the handlers of :data:`KEPT` after the ``with`` block (main thread only:
    elsewhere Python cannot set handlers, nor can an import there have changed them)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    handlers = {s: signal.getsignal(s) for s in KEPT}
    try:
        yield
    finally:
        for s, handler in handlers.items():
            if handler is not None:
                signal.signal(s, handler)
