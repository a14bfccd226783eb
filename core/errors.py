"""The project's error for bad input.

:class:`InputError` is what every stage raises for a file, an option or a value the user
gave that cannot be used: the command line reports it as one line and exits 2. Anything
else that escapes a command is a bug in bbcity (or a library), reported as an internal
error. It is a ``ValueError``, so callers that catch ``ValueError`` keep catching it.
"""

from __future__ import annotations


class InputError(ValueError):
    """Bad input: the message names the file or option and what is wrong with it."""
