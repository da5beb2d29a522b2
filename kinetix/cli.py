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

# kinetix.level.SIZES' names, written out: the CLI parses its arguments before importing JAX
# (tests/kinetix/test_size_classes.py checks that the two agree).
SIZES = ("s", "m", "l", "xl")


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


def non_negative_int(text: str) -> int:
    value = int(text)
    if value < 0:
        raise ValueError(f"{value} is a negative integer")
    return value


def _bench_arguments(parser: argparse.ArgumentParser, *, unit: str, default_steps: int, level_help: str,
                     sizes: tuple[str, ...] = SIZES) -> None:
    """The options every `kinetix bench` throughput command shares; `sizes`: the size classes it can measure."""
    parser.add_argument("--json", action="store_true", help="print results as JSON lines instead of a table")
    parser.add_argument(
        "--sizes",
        type=comma_list(str, allowed=set(sizes)),
        default=["s", "m", "l"],
        help=f"size classes to measure, comma-separated: {', '.join(sizes)} (default: s,m,l)",
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
    parser.add_argument("--devices", type=positive_int, default=None,
                        help="CPU devices to split each batch over (default: one per core; 1 = a single "
                             "computation on one core). A batch they do not divide runs on one device. The "
                             "Python loop always runs in a child process with one device on one core.")
    parser.add_argument("--backend", choices=("cpu", "gpu"), default=None,
                        help="run on this JAX backend (default: JAX's choice, a GPU where there is one); every "
                             "result names the backend and device kind it ran on")
    # Internal: measure only the Python loop (the one-device, one-core child process of the benchmark).
    parser.add_argument("--loop-only", action="store_true", help=argparse.SUPPRESS)


def _bench_engine_arguments(parser: argparse.ArgumentParser) -> None:
    _bench_arguments(parser, unit="physics", default_steps=200,
                     level_help="measure this level file instead of the built-in scenes")


def _bench_env_arguments(parser: argparse.ArgumentParser) -> None:
    _bench_arguments(parser, unit="agent", default_steps=100,
                     level_help="measure this level file (either format) instead of the reference levels",
                     sizes=("s", "m", "l"))  # the reference levels (kinetix.bench.env.REFERENCE_LEVELS)


def _bench_server_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="print one JSON object per line")
    parser.add_argument("--samples", type=positive_int, default=40, help="key presses for the latency (default: 40)")
    parser.add_argument("--sessions", type=positive_int, default=8, help="concurrent playing sessions (default: 8)")
    parser.add_argument("--seconds", type=float, default=5.0, help="seconds per fps measurement (default: 5)")
    parser.add_argument("--chromium", default="/usr/bin/chromium", help="Chromium binary for the latency")
    capacity = parser.add_mutually_exclusive_group()
    capacity.add_argument("--capacity-only", action="store_true",
                          help="measure only the capacity: tabs at >= 25 fps per core with 1 and 2 server processes")
    capacity.add_argument("--no-capacity", action="store_true", help="skip the capacity measurement")


def _serve_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on (default: 127.0.0.1)")
    parser.add_argument("--port", type=int, default=8080, help="port to listen on (default: 8080)")
    parser.add_argument("--data", metavar="DIR", help="directory for saved levels and recordings")
    parser.add_argument("--db", metavar="URL", help="PostgreSQL URL for the gallery (default: SQLite in --data)")
    parser.add_argument("--max-sessions", type=positive_int, default=8,
                        help="most browser tabs served at once; more get a 'server full' message (default: 8)")
    parser.add_argument("--max-training-runs", type=positive_int, default=1,
                        help="training runs (worker processes) at once from 'Train on this level'; more queue "
                             "(default: 1)")
    parser.add_argument("--max-training-queue", type=non_negative_int, default=8,
                        help="training runs waiting in all; beyond it 'Train on this level' is refused (default: 8)")
    parser.add_argument("--max-training-per-client", type=positive_int, default=1,
                        help="training runs of one person (author identity, else tab) running at once; one more "
                             "may wait (default: 1)")
    parser.add_argument("--warm", type=comma_list(str, allowed={*SIZES, "none"}), default=["s", "m", "l"],
                        help="size classes whose play step is compiled before serving (s, m, l, xl), or none (default: "
                             "s,m,l; another size compiles when first played)")
    parser.add_argument("--no-record", dest="record", action="store_false",
                        help="do not record plays (default: every play is recorded to <data>/recordings)")
    # Web safety (server/web/security.py, server/gallery/limits.py); None keeps the server's defaults.
    parser.add_argument("--allowed-hosts", type=comma_list(str), default=[], metavar="NAMES",
                        help="host names or addresses clients may use in the URL besides the --host address, "
                             "localhost and 127.0.0.1 (any port); '*' allows any (not advised: DNS rebinding)")
    parser.add_argument("--trusted-proxies", default="", metavar="ADDRESSES",
                        help="comma-separated addresses or networks of reverse proxies whose X-Forwarded-For, "
                             "-Host and -Proto are believed (the client address for rate limits, the Host and "
                             "Origin checks); '*' any (default: none; docs/deploy.md)")
    parser.add_argument("--root-path", default="", metavar="PATH",
                        help="serve everything under this path (e.g. /kinetix/ behind a proxy that forwards "
                             "/kinetix/...); /kinetix redirects to /kinetix/ (default: the root)")
    parser.add_argument("--write-limit", type=float, default=None, metavar="N",
                        help="gallery writes (save, change, delete, vote) per minute per client address; 0 = no "
                             "limit (default: 60)")
    parser.add_argument("--identity-limit", type=float, default=None, metavar="N",
                        help="new gallery author or voter identities per hour per client address; 0 = no limit "
                             "(default: 10)")
    parser.add_argument("--recent-recordings", type=positive_int, metavar="N",
                        help="most recordings kept in <data>/recordings/recent and in the database's recent "
                             "recordings (tabs' last plays), oldest removed first (default: 32; 500 in a shared "
                             "PostgreSQL database)")
    parser.add_argument("--recent-recordings-mb", type=positive_int, metavar="MB",
                        help="most megabytes kept in <data>/recordings/recent and in the database's recent "
                             "recordings, oldest removed first (default: 64; 256 in a shared PostgreSQL database)")


def _validate_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("files", nargs="+", metavar="FILE", help="level files, in our format or the Kinetix JSON")
    parser.add_argument("--steps", type=positive_int, default=1000, help="physics steps to simulate (default: 1000)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the random actions (default: 0)")


def _convert_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("input", metavar="IN", help="level file to read (format detected from its content)")
    parser.add_argument("output", metavar="OUT", help="file to write (replaced atomically)")
    parser.add_argument("--to", choices=["ours", "kinetix"], help="format to write (default: the other one)")
    parser.add_argument("--size", choices=list(SIZES), help="size class to write (default: the input's)")


def _play_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--agent", required=True, metavar="DIR|noop|random|general",
                        help="who plays: noop, random, general or a checkpoint directory")
    parser.add_argument("--level", required=True, metavar="FILE", help="level file (either format)")
    parser.add_argument("--record", required=True, metavar="OUT.mcap", help="recording to write (atomically)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the reset and the policy (default: 0)")
    parser.add_argument("--max-steps", type=positive_int, help="stop after this many steps (default: the level's)")


def _replay_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", metavar="FILE", help="an .mcap recording")
    parser.add_argument("--gif", metavar="OUT.gif", help="also write the re-simulated play as a GIF")
    parser.add_argument("--mp4", metavar="OUT.mp4", help="also write an MP4 (needs imageio-ffmpeg)")
    parser.add_argument("--resolution", type=positive_int, default=256, help="video size in pixels (default: 256)")


def _export_demos_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--in", dest="inputs", nargs="+", required=True, metavar="DIR_OR_FILE",
                        help="recordings (.mcap files, or directories searched for them)")
    parser.add_argument("--out", required=True, metavar="DIR", help="dataset directory to write")
    parser.add_argument("--size", choices=list(SIZES), help="size class of the observations (default: largest)")
    parser.add_argument("--solved-only", action="store_true", help="keep only recordings that solve their level")
    parser.add_argument("--obs", choices=["entity", "flat", "pixels"], default="flat", help="observation type")
    parser.add_argument("--shard-steps", type=positive_int, default=100_000, help="steps per .npz shard")


def _train_bc_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", required=True, metavar="DIR", help="a dataset from kinetix export-demos")
    parser.add_argument("--out", required=True, metavar="DIR", help="checkpoint directory to write")
    parser.add_argument("--epochs", type=positive_int, default=20, help="passes over the data (default: 20)")
    parser.add_argument("--batch-size", type=positive_int, default=256, help="minibatch size (default: 256)")
    parser.add_argument("--lr", type=float, default=3e-4, help="Adam learning rate (default: 3e-4)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")


def _bench_record_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--level", default="levels/car_ramp.json", metavar="FILE", help="level to play")
    parser.add_argument("--frames", type=positive_int, default=300, help="frames to measure (default: 300)")
    parser.add_argument("--fps", type=float, default=30.0, help="session frame rate (default: 30)")


def _train_arguments(parser: argparse.ArgumentParser) -> None:
    # Settings that define the run default to None here: `--resume DIR` fills the ones not given from the saved
    # run (and refuses ones that differ); kinetix.agents.train.run applies the defaults named in the help.
    parser.add_argument("--level", metavar="FILE|DIR|random-s|random-m|random-l|random-all",
                        help="a level file, a directory of level files, or random levels of a size class "
                             "(required unless --resume)")
    parser.add_argument("--steps", type=positive_int, default=None,
                        help="env steps to train (default: 1000000); with --resume, a new total extends (or "
                             "shortens) the run, and an annealed learning rate follows the new total's schedule")
    parser.add_argument("--out", metavar="DIR", help="output directory (default: runs/<level>-<time>)")
    parser.add_argument("--curriculum", choices=["dr", "sfl", "plr"],
                        help="for random levels: domain randomisation (default), sampling for learnability, "
                             "prioritized level replay")
    parser.add_argument("--sfl-refresh-every", type=positive_int, default=None, metavar="UPDATES",
                        help="sfl: score fresh levels and refill the buffer every UPDATES updates (default: 50, sized "
                             "for 32-64 envs; with 512 envs 10 refreshes as often per env step)")
    parser.add_argument("--sfl-candidates", type=positive_int, default=None, metavar="N",
                        help="sfl: fresh levels scored at each refresh (default: 128; the reference scores 12,288)")
    parser.add_argument("--sfl-attempts", type=positive_int, default=None, metavar="N",
                        help="sfl: episodes per candidate level when scoring its learnability p(1-p) (default: 4, "
                             "so p is one of 0, 1/4, ... 1; more attempts give a finer p at a costlier refresh)")
    parser.add_argument("--buffer-size", type=positive_int, default=None, metavar="N",
                        help="sfl and plr: levels kept in the buffer (default: 64; for sfl at most --sfl-candidates)")
    parser.add_argument("--init", metavar="general|DIR", help="fine-tune this agent instead of starting from scratch")
    parser.add_argument("--seed", type=int, default=None, help="random seed (default: 0)")
    parser.add_argument("--num-envs", type=positive_int, default=None,
                        help="parallel environments (default: 32); with --resume, the count from then on (a bigger "
                             "batch on a GPU: the environments restart on fresh levels)")
    parser.add_argument("--num-steps", type=positive_int, default=None, help="rollout length per update (default: 64)")
    parser.add_argument("--updates-per-call", type=positive_int, default=None,
                        help="updates per jitted chunk between progress reports (default: 4)")
    parser.add_argument("--lr", type=float, default=None,
                        help="Adam learning rate (default: 3e-4); with --resume, the rate from then on (annealed: "
                             "the new rate's line at the same update)")
    parser.add_argument("--ent-coef", type=float, default=None,
                        help="weight of the entropy bonus in the PPO loss (default: 0.01); with --resume, the weight "
                             "from then on")
    parser.add_argument("--gamma", type=float, default=None,
                        help="discount per step in the returns and GAE (default: 0.99; the reference general agent "
                             "0.995); part of what a run optimises, so --resume refuses a change")
    parser.add_argument("--gae-lambda", type=float, default=None, metavar="LAMBDA",
                        help="GAE's lambda (default: 0.95; the reference general agent 0.9); --resume refuses a "
                             "change")
    parser.add_argument("--constant-lr", action="store_const", const=True, default=None,
                        help="keep the learning rate constant instead of annealing it linearly to 0 over the run "
                             "(a run extended with --resume --steps then equals one planned that long)")
    parser.add_argument("--network", choices=["entity", "flat", "pixels"], default=None,
                        help="policy network (default: entity, permutation-invariant)")
    parser.add_argument("--width", type=positive_int, default=None, help="network layer width (default: 64)")
    parser.add_argument("--hidden", type=positive_int, default=None, help="network hidden size (default: 128)")
    parser.add_argument("--activation", choices=["tanh", "relu"], default=None,
                        help="hidden layers' activation (default: tanh; relu units can die for good, see "
                             "kinetix.agents.networks)")
    parser.add_argument("--pooled-norm", action=argparse.BooleanOptionalAction, default=None,
                        help="entity network: a LayerNorm on the pooled entity summary before the actor and critic "
                             "(default: on; without it the summary grows in training and saturates the heads, see "
                             "kinetix.agents.networks)")
    parser.add_argument("--update-epochs", type=positive_int, default=None, help="PPO epochs per update (default: 4)")
    parser.add_argument("--num-minibatches", type=positive_int, default=None,
                        help="PPO minibatches per epoch (default: 4)")
    parser.add_argument("--observation", choices=["entity", "flat", "pixels"], default=None,
                        help="observation type (default: the network's)")
    parser.add_argument("--dense-reward", type=float, default=None,
                        help="shaping scale (default: the level's; 0.1 on random levels)")
    parser.add_argument("--size-groups", action=argparse.BooleanOptionalAction, default=None,
                        help="random-all: step each size class's levels in its own third of the envs at its own size "
                             "(default; 2x faster physics than padding every level to l) or, with --no-size-groups, "
                             "all padded to l in one batch (runs started before 29 Nov 2026; a resumed run keeps "
                             "its own)")
    parser.add_argument("--no-shard", action="store_true", help="do not split the env batch over local devices")
    parser.add_argument("--devices", type=positive_int, default=None,
                        help="CPU devices to split the env batch over (default: one per core in a single-process "
                             "run, one per process with --coordinator/--num-processes; XLA_FLAGS wins)")
    parser.add_argument("--minutes", type=float, default=None,
                        help="stop after this much wall-clock time, compiling included (default: no limit)")
    parser.add_argument("--target-solve-rate", type=float, default=None, metavar="RATE",
                        help="stop once the training solve rate averages RATE over the last 8 updates")
    parser.add_argument("--resume", metavar="DIR",
                        help="continue the run in DIR (its output directory) from its last checkpoint; settings "
                             "not given are the run's own, settings given must equal them but --steps, "
                             "--update-epochs, --num-minibatches, --lr, --ent-coef and --num-envs")
    parser.add_argument("--checkpoint-every", type=float, default=None, metavar="MINUTES",
                        help="also write the checkpoint and training state every MINUTES of wall-clock time "
                             "(default: only at the end)")
    parser.add_argument("--checkpoint-every-updates", type=positive_int, default=None, metavar="N",
                        help="also write them every N updates (rounded up to whole chunks)")
    parser.add_argument("--coordinator", metavar="HOST:PORT",
                        help="multi-host training: address of process 0's coordinator (with --num-processes and "
                             "--process-id; without all three, a cluster environment JAX detects is used)")
    parser.add_argument("--num-processes", type=positive_int, default=None, help="multi-host: processes in all")
    parser.add_argument("--process-id", type=int, default=None, help="multi-host: this process's index, 0..N-1")
    parser.add_argument("--record-command", action="store_true", default=True, help=argparse.SUPPRESS)


def _eval_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--agent", required=True, metavar="DIR|noop|random|general",
                        help="a checkpoint directory, noop, random or general")
    parser.add_argument("--level", required=True, action="append", metavar="FILE|DIR",
                        help="a level file, a directory of level files, or generated-s|m|l|all: 30 held-out "
                             "generated levels per size class that doing nothing does not solve (repeatable)")
    parser.add_argument("--attempts", type=positive_int, default=20, help="episodes per level (default: 20)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
    parser.add_argument("--deterministic", action="store_true", help="take the most likely action (default: sample)")
    parser.add_argument("--json", action="store_true", help="print one JSON object per level")


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
        "server.bench.server:run",
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
    Command(("play",), "play a level with an agent and record the episode to an MCAP file",
            "kinetix.recording.play:run_play", _play_arguments),
    Command(("replay",), "re-simulate a recording, check it bitwise and optionally write a GIF or MP4",
            "kinetix.recording.play:run_replay", _replay_arguments),
    Command(("export-demos",), "turn recordings into a demonstration dataset (.npz shards and a manifest)",
            "kinetix.recording.demos:run", _export_demos_arguments),
    Command(("train-bc",), "behaviour cloning with the PPO network on an export-demos dataset",
            "kinetix.recording.bc:run", _train_bc_arguments),
    Command(("bench", "record"), "measure what recording adds per frame to a session-like loop",
            "kinetix.bench.record:run", _bench_record_arguments),
]


def _bench_train_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="print results as JSON lines")
    parser.add_argument("--sizes", type=comma_list(str, allowed={*SIZES, "all", "all-padded"}), default=["s", "m", "l"],
                        help="size classes to measure, comma-separated (default: s,m,l); all: random-all in size "
                             "groups, as kinetix train runs it; all-padded: every level padded to l")
    parser.add_argument("--num-envs", type=positive_int, default=32, help="parallel environments (default: 32)")
    parser.add_argument("--num-steps", type=positive_int, default=64, help="rollout length (default: 64)")
    parser.add_argument("--updates-per-call", type=positive_int, default=4, help="updates per chunk (default: 4)")
    parser.add_argument("--update-epochs", type=positive_int, default=None,
                        help="PPO epochs per update (default: kinetix train's, 4)")
    parser.add_argument("--num-minibatches", type=positive_int, default=None,
                        help="minibatches per epoch (default: kinetix train's, 4); the general run uses 32")
    parser.add_argument("--chunks", type=positive_int, default=3, help="timed chunks after the first (default: 3)")
    parser.add_argument("--devices", type=positive_int, default=None,
                        help="CPU devices to split the env batch over (default: one per core, as bench env)")
    parser.add_argument("--env", action="store_true",
                        help="also measure `kinetix bench env`'s rollout at the same size and batch in the same run, "
                             "and print the share of it that training keeps")


def _bench_gym_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true", help="print results as JSON lines instead of a table")
    parser.add_argument("--sizes", type=comma_list(str, allowed={"s", "m", "l"}), default=["s", "m", "l"],
                        help="size classes whose reference level to measure, comma-separated (default: s,m,l)")
    parser.add_argument("--level", metavar="FILE", help="measure this level file instead of the reference levels")
    parser.add_argument("--batches", type=comma_list(positive_int), default=[512],
                        help="numbers of environments, comma-separated (default: 512)")
    parser.add_argument("--steps", type=positive_int, default=100, help="agent steps per measurement (default: 100)")
    parser.add_argument("--observation", choices=["entity", "flat", "pixels"], default="entity",
                        help="the gym env's observation type (default: entity)")
    parser.add_argument("--devices", type=positive_int, default=None,
                        help="CPU devices to split each batch over, for both envs (default: one per core)")
    parser.add_argument("--backend", choices=("cpu", "gpu"), default=None,
                        help="run on this JAX backend (default: JAX's choice, a GPU where there is one)")


COMMANDS += [
    Command(("bench", "gym"), "measure the Gymnasium vector env (kinetix.gym) against the JAX env at one batch",
            "kinetix.bench.gym:run", _bench_gym_arguments),
    Command(("bench", "train"), "measure PPO training throughput (env steps/s including updates) per size class",
            "kinetix.agents.bench:run", _bench_train_arguments),
    Command(("train",), "train a PPO agent on a level, a directory of levels or random levels",
            "kinetix.agents.train:run", _train_arguments),
    Command(("eval",), "solve rate of an agent over 20 attempts per level", "kinetix.agents.evaluate:run",
            _eval_arguments),
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
    if getattr(args, "devices", None) is None and (getattr(args, "coordinator", None)
                                                   or getattr(args, "num_processes", None)):
        args.devices = 1  # several processes on one machine: each already has its share of the cores
    if getattr(args, "devices", False) is not False:  # before JAX starts: XLA reads the flag once
        from kinetix.devices import confine_to_one_core, request_cpu_devices

        request_cpu_devices(args.devices)
        if getattr(args, "loop_only", False):  # the benches' interactive-loop child (interactive_loops)
            confine_to_one_core()
    if command.uses_jax:  # before JAX starts: it tries only the platforms present (no "Unable to ... 'tpu'")
        from kinetix.devices import use_present_platforms

        use_present_platforms()
    if getattr(args, "backend", None) is not None:  # before JAX starts: "cpu" hides the other backends
        from kinetix.devices import BackendError, select_backend

        try:
            select_backend(args.backend)
        except BackendError as error:
            print(f"kinetix {' '.join(command.path)}: {error}", file=sys.stderr)
            return 2
    if command.uses_jax:
        from kinetix.jaxcache import enable_compilation_cache

        enable_compilation_cache()
    return run(args) or 0


if __name__ == "__main__":
    sys.exit(main())
