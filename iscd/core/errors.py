"""Errors every layer may raise for the command line to report.

:class:`UserError` is the one the ``iscd`` command turns into one line on stderr and exit
status 2 (a bad file, a bad option, a device that is not there); it lives here, below
everything, so that no layer imports the command line to raise it.
"""

from __future__ import annotations


class UserError(Exception):
    """An error caused by the user's input: printed as one line, exit status 2."""
