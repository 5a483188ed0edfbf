"""The analysts' SQL surface: ``python -m pipeline.sql STORE`` (shell, ``-c``, ``-f``, ``--audit``,
``--export-duckdb``, ``--init-script``) over the relations and views of :func:`pipeline.db.connect`."""
