"""mypy over every module of the checkout under its import name: ``python -m tests.typecheck``.

mypy finds a module by its folder's name, and the editable install reaches ``embedrl.train`` in ``train/``
through an import hook that mypy does not run; so each file is handed to mypy with its import name, and the
options come from pyproject.toml as usual. Prints mypy's messages; exit 1 when there are any.
"""

from __future__ import annotations

import sys

from mypy import build
from mypy.errors import CompileError
from mypy.main import process_options
from mypy.modulefinder import BuildSource

from tests.source_tree import REPO, modules


def main(argv: list[str]) -> int:
    _, options = process_options(["--config-file", str(REPO / "pyproject.toml"), *argv])
    sources = [BuildSource(str(path), name) for name, path in modules().items()]
    try:
        messages = build.build(sources, options).errors
    except CompileError as error:
        messages = error.messages
    for message in messages:
        print(message)
    print(f"mypy: {len(messages)} messages in {len(sources)} modules")
    return 1 if messages else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
