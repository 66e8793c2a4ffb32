"""Exceptions of the ``export`` package; the CLI prints them as one-line ``error: ...`` messages.

- :class:`ExportError`: base class.
  - :class:`UnsupportedModelError`: the source (SB3 model, policy class, spaces) is not supported.
  - :class:`InvalidModelError`: the file is missing, truncated, not ONNX, or holds NaN/Inf weights.
  - :class:`UnsupportedOpError`: an ONNX op, attribute, dtype or shape the code generator cannot handle.
  - :class:`UnrepresentableRangeError`: a quantised layer's scales do not fit its integer encoding.
  - :class:`BuildError`: the generated C did not compile.
  - :class:`VerificationError`: a verification step exceeded its tolerance.
"""


class ExportError(Exception):
    """Base class of every error the ``export`` package raises on purpose."""


class UnsupportedModelError(ExportError):
    """The source model is of a kind the exporter does not handle; the message says what is supported."""


class InvalidModelError(ExportError):
    """The source file cannot be read as a valid model."""


class UnsupportedOpError(ExportError):
    """The ONNX graph uses an op, attribute, dtype or shape outside the supported set."""


class UnrepresentableRangeError(ExportError):
    """A layer's calibrated scales (a requantisation multiplier, a bias in accumulator units) cannot be
    represented by the integer scheme; the message names the layer."""


class BuildError(ExportError):
    """Compiling the generated C failed; the message carries the compiler's output."""


class VerificationError(ExportError):
    """A verification step (ONNX vs SB3, C vs onnxruntime, closed loop) failed its bound."""
