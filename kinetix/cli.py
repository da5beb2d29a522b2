"""The `kinetix` command line: thin argument parsing that hands each command to a library module.

Commands are listed in COMMANDS. Each one names its implementation as "module:function" and that
module is imported only when the command runs, so `kinetix --help` is fast and does not import JAX.
To add a command, write an `add_arguments` function and append a `Command` to COMMANDS.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Callable
from dataclasses import dataclass


def _no_arguments(parser: argparse.ArgumentParser) -> None:
    pass


@dataclass(frozen=True)
class Command:
    path: tuple[str, ...]  # words on the command line, e.g. ("bench", "engine")
    help: str
    target: str  # "module:function" called with the parsed arguments; returns an exit code or None
    add_arguments: Callable[[argparse.ArgumentParser], None] = _no_arguments
    uses_jax: bool = True  # turn on the persistent compilation cache before running


class CommandUnavailable(Exception):
    """The module implementing a command does not exist (yet)."""


def comma_list(item_type: Callable[[str], object], allowed: set[str] | None = None) -> Callable[[str], list]:
    """An argparse `type` reading "a,b,c" into a list of `item_type`, optionally restricted to `allowed` words."""

    def parse(text: str) -> list:
        words = [word.strip() for word in text.split(",") if word.strip()]
        if not words:
            raise argparse.ArgumentTypeError("expected a comma-separated list")
        if allowed is not None and (unknown := sorted(set(words) - allowed)):
            raise argparse.ArgumentTypeError(f"unknown {', '.join(unknown)}; choose from {', '.join(sorted(allowed))}")
        try:
            return [item_type(word) for word in words]
        except ValueError as error:
            raise argparse.ArgumentTypeError(str(error)) from None

    return parse


def positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise ValueError(f"{value} is not a positive integer")
    return value


def _bench_arguments(parser: argparse.ArgumentParser, *, unit: str, default_steps: int, level_help: str) -> None:
    """The options every `kinetix bench` throughput command shares."""
    parser.add_argument("--json", action="store_true", help="print results as JSON lines instead of a table")
    parser.add_argument(
        "--sizes",
        type=comma_list(str, allowed={"s", "m", "l"}),
        default=["s", "m", "l"],
        help="size classes to measure, comma-separated (default: s,m,l)",
    )
    parser.add_argument(
        "--batches",
        type=comma_list(positive_int),
        default=[1, 16, 256, 2048],
        help="numbers of parallel scenes, comma-separated (default: 1,16,256,2048)",
    )
    parser.add_argument("--level", metavar="FILE", help=level_help)
    parser.add_argument("--steps", type=positive_int, default=default_steps,
                        help=f"{unit} steps per measurement (default: {default_steps})")


def _bench_engine_arguments(parser: argparse.ArgumentParser) -> None:
    _bench_arguments(parser, unit="physics", default_steps=200,
                     level_help="measure this level file instead of the built-in scenes")


def _bench_env_arguments(parser: argparse.ArgumentParser) -> None:
    _bench_arguments(parser, unit="agent", default_steps=100,
                     level_help="measure this level file (either format) instead of the reference levels")


def _bench_server_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="print one JSON object per line")
    parser.add_argument("--samples", type=positive_int, default=40, help="key presses for the latency (default: 40)")
    parser.add_argument("--sessions", type=positive_int, default=8, help="concurrent playing sessions (default: 8)")
    parser.add_argument("--seconds", type=float, default=5.0, help="seconds per fps measurement (default: 5)")
    parser.add_argument("--chromium", default="/usr/bin/chromium", help="Chromium binary for the latency")


def _serve_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on (default: 127.0.0.1)")
    parser.add_argument("--port", type=int, default=8080, help="port to listen on (default: 8080)")
    parser.add_argument("--data", metavar="DIR", help="directory for saved levels and recordings")
    parser.add_argument("--db", metavar="URL", help="PostgreSQL URL for the gallery (default: SQLite in --data)")
    parser.add_argument("--max-sessions", type=positive_int, default=8,
                        help="most browser tabs served at once; more get a 'server full' message (default: 8)")
    parser.add_argument("--warm", type=comma_list(str, allowed={"s", "m", "l", "none"}), default=["s", "m", "l"],
                        help="size classes whose play step is compiled before serving, or none (default: s,m,l)")


def _validate_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("files", nargs="+", metavar="FILE", help="level files, in our format or the Kinetix JSON")
    parser.add_argument("--steps", type=positive_int, default=1000, help="physics steps to simulate (default: 1000)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the random actions (default: 0)")


def _convert_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("input", metavar="IN", help="level file to read (format detected from its content)")
    parser.add_argument("output", metavar="OUT", help="file to write (replaced atomically)")
    parser.add_argument("--to", choices=["ours", "kinetix"], help="format to write (default: the other one)")
    parser.add_argument("--size", choices=["s", "m", "l"], help="size class to write (default: the input's)")


COMMANDS: list[Command] = [
    Command(
        ("bench", "engine"),
        "measure physics steps per second across size classes and batch sizes",
        "kinetix.bench.engine:run",
        _bench_engine_arguments,
    ),
    Command(
        ("bench", "env"),
        "measure environment steps per second, env.step latency, compile times and the pixel renderer",
        "kinetix.bench.env:run",
        _bench_env_arguments,
    ),
    Command(
        ("bench", "server"),
        "measure the browser server: draw time, key-to-frame latency in Chromium, fps and RSS with 8 sessions",
        "server.bench:run",
        _bench_server_arguments,
    ),
    Command(("serve",), "start the browser editor and playground", "server.app:serve", _serve_arguments),
    Command(
        ("validate",),
        "load level files and simulate them with random actions; exit status 1 if any fails",
        "kinetix.validate:run",
        _validate_arguments,
    ),
    Command(
        ("convert",),
        "convert a level file between our format and the public Kinetix JSON",
        "kinetix.convert:run",
        _convert_arguments,
    ),
]

GROUP_HELP = {("bench",): "measure performance"}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="kinetix", description="2D physics playground for reinforcement learning.")
    parser.set_defaults(command=None, group_parser=parser)
    groups: dict[tuple[str, ...], argparse.ArgumentParser] = {(): parser}
    subparsers: dict[tuple[str, ...], argparse._SubParsersAction] = {}

    def add_child(group: tuple[str, ...], name: str, help_text: str) -> argparse.ArgumentParser:
        if group not in subparsers:
            subparsers[group] = groups[group].add_subparsers(title="commands", metavar="COMMAND")
        return subparsers[group].add_parser(name, help=help_text, description=help_text)

    for command in COMMANDS:
        *group, name = command.path
        for depth in range(1, len(group) + 1):
            path = tuple(group[:depth])
            if path not in groups:
                groups[path] = add_child(path[:-1], path[-1], GROUP_HELP.get(path, ""))
                groups[path].set_defaults(group_parser=groups[path])
        leaf = add_child(tuple(group), name, command.help)
        command.add_arguments(leaf)
        leaf.set_defaults(command=command)
    return parser


def _load(target: str) -> Callable:
    """Import "module:function", raising CommandUnavailable only when that module itself is missing."""
    module_name, function_name = target.split(":")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as error:
        # A missing dependency inside an existing module is a real error, not an unavailable command.
        if error.name is None or not (module_name == error.name or module_name.startswith(error.name + ".")):
            raise
        raise CommandUnavailable(f"module {module_name} is missing") from None
    return getattr(module, function_name)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    command: Command | None = args.command
    if command is None:
        args.group_parser.print_help(sys.stderr)
        return 2
    try:
        run = _load(command.target)
    except CommandUnavailable as error:
        print(f"kinetix {' '.join(command.path)} is not available yet: {error}", file=sys.stderr)
        return 2
    if command.uses_jax:
        from kinetix.jaxcache import enable_compilation_cache

        enable_compilation_cache()
    return run(args) or 0


if __name__ == "__main__":
    sys.exit(main())
