"""``python -m pipeline.serve STORE``: the query path as an HTTP service (FastAPI + uvicorn) with a web page.

Modules: :mod:`~pipeline.serve.cli` (options, safety checks, uvicorn), :mod:`~pipeline.serve.app`
(routes), :mod:`~pipeline.serve.service` (snapshots, hot reload, worker pool, statistics),
:mod:`~pipeline.serve.guard` (token, body limit), ``static/index.html`` (the page). See ``docs/serve.md``.
"""
