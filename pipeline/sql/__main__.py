"""``python -m pipeline.sql STORE``: a DuckDB shell over an OSCAR store (see ``--help``)."""

import sys

from pipeline.sql.cli import main

sys.exit(main())
