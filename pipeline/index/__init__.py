"""The stage-1 vector index: built from the text-embedding Delta table, kept in step with its commits.

:mod:`~pipeline.index.build` builds it, :mod:`~pipeline.index.sync` applies new commits,
:mod:`~pipeline.index.snapshot` answers stage 1 from it, :mod:`~pipeline.index.choose` picks the exact
path or the index (``--stage1``). ``python -m pipeline.index build|sync|status STORE`` (docs/cli.md).
"""
