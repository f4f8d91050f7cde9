"""``python -m vastray``: the same as the ``vastray`` command."""

import sys

from vastray.cli import main

sys.exit(main())
