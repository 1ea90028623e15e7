"""The ``albcap`` command: one entry point, subcommands contributed by each part of the project.

Each part keeps its command-line front end beside its code (``model/cli.py``, ``sim/cli.py``, ...)
and exposes ``register(subparsers)`` for top-level commands and, optionally,
``register_bench(bench_subparsers)`` for ``albcap bench TARGET``. This module only collects them,
so adding a command never means editing someone else's file.
"""

from __future__ import annotations

import argparse
import importlib
import sys

__all__ = ["main"]

#: Modules contributing subcommands, in help order.
COMMAND_MODULES = (
    "model.cli",
    "model.accuracy_cli",
    "sim.cli",
    "hdl.cli",
    "firmware_host.commands",
    "firmware_host.survey",
    "firmware_host.cosim",
)


def _build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="albcap",
        description="Airborne lidar bathymetry digitizer: model, simulator, HDL and host tool.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    bench = sub.add_parser("bench", help="measured benchmarks (print figures, JSON with --json)")
    bench_sub = bench.add_subparsers(dest="bench_target", metavar="TARGET", required=True)
    for name in COMMAND_MODULES:
        try:
            mod = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name == name:  # part not written yet; its commands are simply absent
                continue
            raise
        if hasattr(mod, "register"):
            mod.register(sub)
        if hasattr(mod, "register_bench"):
            mod.register_bench(bench_sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run ``albcap``; returns the process exit status.

    Commands set ``func`` on their parsed arguments; a ``ValueError`` or ``OSError`` raised by a
    command becomes a one-line error on stderr and exit status 2, never a traceback.
    """
    parser = _build_parser()
    args = parser.parse_args(argv)
    try:
        status = args.func(args)
    except (ValueError, OSError) as exc:
        print(f"albcap {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    return int(status or 0)


if __name__ == "__main__":
    sys.exit(main())
