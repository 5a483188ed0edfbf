"""``oscar VERB [ARGS...]``: one console command over the ``python -m pipeline.<verb>`` entry points.

``oscar onboard LIB --store S`` runs exactly ``python -m pipeline.onboard LIB --store S`` (same options,
output and exit codes). A verb is one row of :data:`COMMANDS`; a verb whose module is not in this
installation gives a one-line error. Only the standard library is imported here, so ``oscar --help`` is
instant.
"""

from __future__ import annotations

import sys

# verb -> (module run as ``python -m``, one-line summary)
COMMANDS: dict[str, tuple[str, str]] = {
    "onboard": ("pipeline.onboard", "render, caption and embed the new meshes of a library (incremental)"),
    "query": ("pipeline.query", "rank the CAD models of a store for a photo and a prompt"),
    "evaluate": ("pipeline.evaluate", "metrics, sweeps and reports on labelled queries"),
    "sql": ("pipeline.sql", "DuckDB over a store: shell, -c/-f, ready audits"),
    "compact": ("pipeline.compact", "merge a store's parts and drop superseded rows"),
    "serve": ("pipeline.serve", "HTTP query service and web page"),
    "migrate": ("pipeline.migrate", "upgrade a store to the current layout"),
    "fsck": ("pipeline.fsck", "check a store for missing or corrupt files"),
    "handoff": (
        "pipeline.handoff",
        "answers -> BOP models (mm) + per-query pose priors for a pose estimator",
    ),
}


def available(module: str) -> bool:
    """Whether ``module`` exists in this installation (found without importing it)."""
    from importlib.util import find_spec

    try:
        return find_spec(module) is not None
    except ImportError:
        return False


def usage() -> str:
    """The ``--help`` text: the verbs this installation has."""
    rows = [f"  {verb:<9} {summary}" for verb, (mod, summary) in COMMANDS.items() if available(mod)]
    return (
        "usage: oscar VERB [ARGS...]   (same as python -m pipeline.VERB ARGS...)\n\n"
        "OSCAR: open-set CAD retrieval from a language prompt and a single image.\n\n"
        "verbs:\n" + "\n".join(rows) + "\n\n`oscar VERB --help` lists a verb's options (docs/cli.md)."
    )


def main(argv: list[str] | None = None) -> int:
    """Dispatch ``argv`` (default ``sys.argv[1:]``) to the verb's ``python -m`` main; returns its exit code."""
    import runpy

    args = sys.argv[1:] if argv is None else list(argv)
    if not args or args[0] in ("-h", "--help", "help"):
        try:
            print(usage(), flush=True)
        except BrokenPipeError:  # `oscar --help | head`
            import os

            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0 if args else 2
    if args[0] == "--version":
        from pipeline import __version__

        print(f"oscar {__version__}")
        return 0
    verb, rest = args[0], args[1:]
    if verb not in COMMANDS:
        print(f"error: unknown verb {verb!r}; verbs: {', '.join(COMMANDS)} (oscar --help)", file=sys.stderr)
        return 2
    module = COMMANDS[verb][0]
    if not available(module):
        print(
            f"error: `oscar {verb}` is not available in this installation (no module {module})",
            file=sys.stderr,
        )
        return 2
    saved = sys.argv
    sys.argv = [f"oscar {verb}", *rest]  # runpy puts the module file first, as python -m does
    try:
        runpy.run_module(module, run_name="__main__", alter_sys=True)
    except SystemExit as exc:
        code = exc.code
        if code is None or isinstance(code, int):
            return code or 0
        print(code, file=sys.stderr)  # sys.exit("message")
        return 1
    finally:
        sys.argv = saved
    return 0


if __name__ == "__main__":
    sys.exit(main())
