"""Exceptions of the ``train`` package; the CLI turns them into one-line ``error:`` messages.

- :class:`TrainError`: base class.
  - :class:`UsageError`: a command was asked for something it cannot do (the message says what can).
  - :class:`ModelFileError`: a trained model's file cannot be used.
    - :class:`InvalidModelFileError`: missing, truncated, or not what it claims to be.
    - :class:`UnsupportedModelFileError`: a valid model of a kind embedrl does not handle.
"""


class TrainError(Exception):
    """Base class of every error the ``train`` package raises on purpose."""


class UsageError(TrainError):
    """Invalid or unsupported request: bad argument values, unsupported file types, missing features."""


class ModelFileError(TrainError):
    """A trained model's file cannot be used; the message names the file."""


class InvalidModelFileError(ModelFileError):
    """The file is missing, truncated, or not a Stable-Baselines3 model or statistics file."""


class UnsupportedModelFileError(ModelFileError):
    """A valid model of a kind embedrl does not handle; the message says what is supported."""
