"""``python -m pipeline.onboard``: see :mod:`pipeline.onboard.cli`."""

import sys

from pipeline.onboard.cli import main

sys.exit(main())
