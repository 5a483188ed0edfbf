"""``python -m pipeline.serve``: see :mod:`pipeline.serve.cli`."""

import sys

from pipeline.serve.cli import main

sys.exit(main())
