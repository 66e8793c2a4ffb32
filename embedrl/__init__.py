"""embedrl: from a reinforcement-learning policy in simulation to an embedded controller on CAN.

The pipeline's packages, bottom to top: :mod:`embedrl.common` (shared utilities), :mod:`embedrl.train`
(environments, scenario specs, agents, evaluation), :mod:`embedrl.export` (policy -> ONNX -> C),
:mod:`embedrl.hil` (CAN database, sandboxes, hardware in the loop); :mod:`embedrl.cli` is the command.
Lower layers never import upper ones.

In the source repository the packages are its top-level folders (``train/``, ``export/``, ``hil/``, and
the C runtime ``runtime_c/``, shipped as package data), mapped onto these names by pyproject.toml's
``package-dir``; a wheel holds them as ordinary folders inside this package.
"""

from __future__ import annotations


def __getattr__(name: str) -> str:
    """``__version__``, read from the installed distribution's metadata when first asked for (importlib's
    metadata reader is not imported by a program that never asks, e.g. a HIL session in an emulated guest)."""
    if name != "__version__":
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    from importlib import metadata

    try:
        version = metadata.version("embedrl")
    except metadata.PackageNotFoundError:
        version = "0+unknown"
    globals()["__version__"] = version
    return version
