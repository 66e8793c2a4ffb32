"""``python -m embedrl``: the ``embedrl`` command."""

import sys

from embedrl.cli import main

sys.exit(main())
