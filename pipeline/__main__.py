"""``python -m pipeline VERB ...``: the same as the ``oscar`` console command (:mod:`pipeline.cli`)."""

import sys

from pipeline.cli import main

sys.exit(main())
