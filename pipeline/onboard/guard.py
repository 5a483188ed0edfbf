"""The mass-removal guard: a run that would mark too many of a library's active meshes removed stops
before it commits anything.

A network share that is not mounted looks like an empty library folder; without the guard, a nightly run
would mark every mesh removed and a running service would reload to an empty library. The guard counts
the active files of the library that the run no longer finds (files that changed content are replaced,
not lost, and files that fail discovery keep their rows) against ``--max-removed`` (a share of the active
files, 10% by default), and always trips when the library yields no file at all while the store holds
active meshes of it. ``--allow-removal`` turns it off for a run that removes meshes on purpose.
"""

from __future__ import annotations

from dataclasses import dataclass

#: Default ``--max-removed``: the share of a library's active files one run may mark removed.
DEFAULT_MAX_REMOVED = 0.10


@dataclass(frozen=True)
class RemovalCheck:
    """What the guard saw in one run's plan, and its verdict."""

    active: int  # active files of the library before the run
    vanished: int  # of those, files the library no longer yields
    n_files: int  # files the library yields now (errors included)
    max_share: float
    allowed: bool  # --allow-removal

    @property
    def share(self) -> float:
        return self.vanished / self.active if self.active else 0.0

    @property
    def tripped(self) -> bool:
        """Whether the run must stop before committing anything."""
        if self.allowed or self.vanished == 0:
            return False
        return self.n_files == 0 or self.share > self.max_share

    def describe(self) -> dict:
        """JSON-ready record for the ``runs`` table (``config_json.removal_guard``)."""
        return {
            "active": self.active,
            "vanished": self.vanished,
            "share": round(self.share, 4),
            "max_removed": self.max_share,
            "allow_removal": self.allowed,
            "tripped": self.tripped,
        }

    def line(self) -> str:
        """The run summary's line about the guard."""
        limit = "off (--allow-removal)" if self.allowed else f"limit {self.max_share:.0%}"
        return (
            f"removal guard: {self.vanished} of {self.active} active files vanished "
            f"({self.share:.0%}), {limit}"
        )

    def message(self, library: str) -> str:
        """The one-line error of a run the guard stopped."""
        why = (
            f"library {library} yields no mesh file (a share that is not mounted?)"
            if self.n_files == 0
            else f"more than --max-removed {self.max_share:.0%}"
        )
        return (
            f"removal guard: this run would mark {self.vanished} of {self.active} active files of the library "
            f"removed ({self.share:.0%}): {why}; nothing was committed; pass --allow-removal if the files "
            "were removed on purpose"
        )


class RemovalGuardError(RuntimeError):
    """A run stopped by the removal guard (nothing committed but the run's record)."""

    def __init__(self, check: RemovalCheck, library: str, summary=None):
        super().__init__(check.message(library))
        self.check, self.summary = check, summary


def check_removals(active: int, vanished: int, n_files: int, max_share: float, allowed: bool) -> RemovalCheck:
    """The guard's verdict on a plan (``max_share`` in 0..1)."""
    if not 0.0 <= max_share <= 1.0:
        raise ValueError(f"--max-removed must be a share within 0..1 (or 0%..100%), got {max_share}")
    return RemovalCheck(active, vanished, n_files, max_share, allowed)


def parse_share(text: str) -> float:
    """``--max-removed`` text -> a share in 0..1: ``10%`` or ``0.1`` (a bare number above 1 is refused)."""
    t = text.strip()
    try:
        value = float(t[:-1]) / 100.0 if t.endswith("%") else float(t)
    except ValueError:
        raise ValueError(f"expected a share such as 10% or 0.1, got {text!r}") from None
    if not 0.0 <= value <= 1.0 or value != value:
        raise ValueError(f"expected a share within 0%..100% (0..1), got {text!r}")
    return value
