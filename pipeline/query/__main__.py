"""``python -m pipeline.query``: see :mod:`pipeline.query.cli`."""

import sys

from pipeline.query.cli import main

sys.exit(main())
