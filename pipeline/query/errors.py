"""The one error type of the query path: a user-facing, one-line message (the CLI prints it and exits 2)."""

from __future__ import annotations


class QueryError(ValueError):
    """Bad input or an unusable store/model combination; ``str(exc)`` is one line that says how to fix it."""

    def __init__(self, message: str) -> None:
        super().__init__(" ".join(str(message).split()))


class StoreUnavailable(RuntimeError):
    """The store changed under a query and its newest committed snapshot could not answer either; retry
    later (the service answers 503 with ``Retry-After``). ``str(exc)`` is one line."""

    def __init__(self, message: str) -> None:
        super().__init__(" ".join(str(message).split()))
