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

from importlib import metadata

try:
    __version__ = metadata.version("embedrl")
except metadata.PackageNotFoundError:
    __version__ = "0+unknown"
