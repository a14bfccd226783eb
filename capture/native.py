"""pycolmap, loaded after the native libraries that must come before it, with Python's signal
handlers kept: every user of pycolmap imports it from here (``from capture.native import pycolmap``).

* **Load order.** Open3D and OpenCV must be loaded before pycolmap: with pycolmap first,
  OpenCV's PNG writer crashes (their bundled libpng builds clash).
* **Signals.** pycolmap (through glog) installs crash handlers on import, SIGTERM among them;
  :func:`core.signals.python_signal_handlers` puts Python's back (a terminated run unwinds
  through Python, removing temporaries and stopping pool workers).

Importing it loads Open3D and pycolmap (about a second): :mod:`capture` itself does not.
"""

from __future__ import annotations

import cv2  # noqa: F401  (before pycolmap, see above)
import open3d  # noqa: F401  (before pycolmap, see above)

from core.signals import python_signal_handlers

with python_signal_handlers():  # the first import of pycolmap anywhere
    import pycolmap

__all__ = ["pycolmap"]
