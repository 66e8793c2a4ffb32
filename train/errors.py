"""Exceptions of the ``train`` package; the CLI turns them into one-line ``error:`` messages.

- :class:`TrainError`: base class.
  - :class:`UsageError`: a command was asked for something it cannot do (the message says what can).
"""


class TrainError(Exception):
    """Base class of every error the ``train`` package raises on purpose."""


class UsageError(TrainError):
    """Invalid or unsupported request: bad argument values, unsupported file types, missing features."""
