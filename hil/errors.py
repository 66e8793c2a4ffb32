"""Exceptions of the ``hil`` package; the CLI prints them as one-line ``error: ...`` messages.

- :class:`HilError`: no CAN sandbox, node build or session failure, bad export folder.
"""


class HilError(Exception):
    """Base class of every error the ``hil`` package raises on purpose."""
