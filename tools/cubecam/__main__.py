"""``python -m cubecam``: the same as the ``cubecam`` command."""

import sys

from cubecam.cli import main

sys.exit(main())
