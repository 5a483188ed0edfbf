"""``python -m pipeline.handoff``: see :mod:`pipeline.handoff.cli`."""

import sys

from pipeline.handoff.cli import main

sys.exit(main())
