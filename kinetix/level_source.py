"""What a `--level` argument names: one level file, a directory of level files, or random levels of a size class.

    source = level_source("levels/car_right.json")      # or "levels/" or "random-s"
    env = make_env(source.env_config("entity", "multi_discrete"), source.reset_fn())
    params = source.params

`random-all` draws each level's size class (s, m or l, uniformly), generates it there and pads it to l.
`kinetix train` and `kinetix.gym` resolve levels here, so both build the same environment from the same words.
A directory's levels are brought to the largest size class among them (smaller ones are padded) and must share one
frame skip (it is compile-time); each keeps its own episode length, shaping and actuator scales in `level_params`.
Random levels are generated every episode (kinetix.generate) with shaping RANDOM_DENSE_REWARD, as the public
Kinetix environment.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

import jax
import jax.numpy as jnp

import jax2d
from kinetix.env import EnvConfig, EnvParams, ResetFn
from kinetix.level import WALLS_SOLVER, Level, LevelError, LevelFile, LevelParams, SizeClass, size_class, solver_for
from kinetix.levels import load_level, resize
from kinetix.reset_fns import reset_list, reset_random, reset_single, stack_levels

RANDOM_LEVELS = ("random-s", "random-m", "random-l", "random-all")
# random-all: each level's size class drawn uniformly from these, generated there and padded to the last
# (kinetix.padding), so one compiled program trains on all three.
MIXED_SIZES = ("s", "m", "l")
RANDOM_DENSE_REWARD = 0.1  # shaping on generated levels, as the public Kinetix environment


# Held-out generated levels for evaluation (`kinetix eval --level generated-s`): HELD_OUT_COUNT levels per size class
# that the no-op policy does not solve, from a key no training run draws (a run's levels come from its own seed's
# keys), so the same set every time. They measure an agent on the distribution it trained on, beside the
# hand-made sets.
GENERATED_LEVELS = ("generated-s", "generated-m", "generated-l", "generated-all")
HELD_OUT_SEED = 777
HELD_OUT_COUNT = 30


def held_out_levels(spec: str, count: int = HELD_OUT_COUNT, seed: int = HELD_OUT_SEED) -> list[tuple[str, LevelFile]]:
    """(name, LevelFile) of the held-out generated levels `spec` names (GENERATED_LEVELS; generated-all is s, m
    and l, each in its own size class). Level i of size s is kinetix.generate.sample_nontrivial_level with key
    split(fold_in(PRNGKey(seed), ord("s")), count)[i]; where 8 candidates are all solved by doing nothing the
    last is kept. Settings: LevelParams() (shaping RANDOM_DENSE_REWARD, as in training)."""
    from kinetix.generate import sample_nontrivial_level

    if spec not in GENERATED_LEVELS:
        raise LevelError(f"{spec!r} is not one of {', '.join(GENERATED_LEVELS)}")
    sizes = MIXED_SIZES if spec == "generated-all" else (spec.removeprefix("generated-"),)
    params = LevelParams(dense_reward_scale=RANDOM_DENSE_REWARD)
    named = []
    for name in sizes:
        size = size_class(name)
        keys = jax.random.split(jax.random.fold_in(jax.random.PRNGKey(seed), ord(name)), count)
        levels, _ = jax2d.jit(jax.vmap(lambda k, size=size: sample_nontrivial_level(k, size)))(keys)
        for i in range(count):
            level, label = jax.tree.map(lambda x, i=i: x[i], levels), f"generated-{name}/{i:02d}"
            named.append((label, LevelFile(level, params, size, name=label)))
    return named


def eval_levels(spec: str | Path) -> list[tuple[str, LevelFile]]:
    """(name, LevelFile) for every level an evaluation's `--level` names: a level file, a directory of them, or
    held-out generated levels (GENERATED_LEVELS)."""
    if str(spec) in GENERATED_LEVELS:
        return held_out_levels(str(spec))
    return [(str(p), load_level(p)) for p in level_paths(spec)]


def level_paths(spec: str | Path) -> list[Path]:
    """A level file, or every *.json in a directory (sorted)."""
    path = Path(spec)
    if path.is_dir():
        paths = sorted(path.glob("*.json"))
        if not paths:
            raise LevelError(f"no *.json level files in {path}")
        return paths
    if not path.is_file():
        raise LevelError(f"level {path} does not exist")
    return [path]


@dataclasses.dataclass(frozen=True, eq=False)
class LevelSource:
    """The levels of one `--level` spec and the compile-time settings they need."""

    spec: str
    size: SizeClass
    frame_skip: int
    solver: object  # jax2d SolverConfig: WALLS_SOLVER when every level keeps its walls static
    params: EnvParams  # the first level's (files) or the random levels' settings
    generator: Callable[[jax.Array], Level] | None = None  # random levels only
    files: tuple[LevelFile, ...] = ()  # level files only, each in `size`
    names: tuple[str, ...] = ()
    dense_reward: float | None = None  # the shaping scale given to level_source, if any

    @property
    def random(self) -> bool:
        return self.generator is not None

    @property
    def stacked(self) -> Level:
        """The files' levels stacked on a leading axis (level files only)."""
        return stack_levels(self.files)

    @property
    def level_params(self) -> EnvParams:
        """Every file's EnvParams stacked on a leading axis, in the order of `files` (level files only); a
        `dense_reward` given to `level_source` applies to all."""
        each = [EnvParams.from_level_params(lf.params) for lf in self.files]
        if self.dense_reward is not None:
            each = [dataclasses.replace(p, dense_reward_scale=self.dense_reward) for p in each]
        return jax.tree.map(lambda *xs: jnp.stack([jnp.asarray(x) for x in xs]), *each)

    def env_config(self, observation: str = "entity", action: str = "multi_discrete", **overrides) -> EnvConfig:
        return EnvConfig(self.size, observation=observation, action=action, frame_skip=self.frame_skip,
                         solver=self.solver, **overrides)

    def reset_fn(self) -> ResetFn:
        """Random levels: a new one each episode; one file: always it; several: one drawn uniformly per episode
        (kinetix.reset_fns.reset_list, whose draw `list_index` repeats)."""
        if self.random:
            return reset_random(self.size, self.generator)
        return reset_single(self.files[0]) if len(self.files) == 1 else reset_list(self.stacked)


def level_source(spec: str | Path, dense_reward: float | None = None) -> LevelSource:
    """The levels `spec` names: a level file, a directory of *.json level files, or random-s / random-m / random-l /
    random-all (s, m and l levels, each padded to l).

    dense_reward: the shaping scale for every level (default: each level file's own; RANDOM_DENSE_REWARD for random
    levels). Raises LevelError for a missing, empty or unreadable spec, and for a directory mixing frame skips.
    """
    spec = str(spec)
    if spec in RANDOM_LEVELS:
        from kinetix.generate import sample_level

        if spec == "random-all":
            size, generator = size_class(MIXED_SIZES[-1]), mixed_generator(MIXED_SIZES)
        else:
            size = size_class(spec.removeprefix("random-"))
            generator = lambda key: sample_level(key, size)
        # Generated levels are built on empty_level: their walls are static.
        scale = RANDOM_DENSE_REWARD if dense_reward is None else dense_reward
        return LevelSource(spec, size, LevelParams().frame_skip, WALLS_SOLVER, EnvParams(dense_reward_scale=scale),
                           generator=generator, dense_reward=dense_reward)
    paths = level_paths(spec)
    files = [load_level(p) for p in paths]
    skips = {lf.params.frame_skip for lf in files}
    if len(skips) > 1:
        raise LevelError(f"the levels in {spec} use different frame skips {sorted(skips)}; use them separately")
    largest = max((lf.size for lf in files), key=lambda s: (s.polygons + s.circles, s.joints, s.thrusters))
    files = [lf if lf.size == largest else resize(lf, largest) for lf in files]
    params = EnvParams.from_level_params(files[0].params)
    if dense_reward is not None:
        params = dataclasses.replace(params, dense_reward_scale=dense_reward)
    return LevelSource(spec, largest, skips.pop(), solver_for([lf.level for lf in files]), params, files=tuple(files),
                       names=tuple(p.stem for p in paths), dense_reward=dense_reward)


def mixed_generator(sizes: tuple[str, ...]) -> Callable[[jax.Array], Level]:
    """A generator of levels whose size class is drawn uniformly from `sizes`, padded to the last (the largest).
    Under vmap every class's level is generated and one is kept per row (a select): generation runs once per
    episode, so the 3x is small beside the physics of the episode."""
    from kinetix.generate import sample_level
    from kinetix.padding import pad_level

    classes = [size_class(s) for s in sizes]

    def generator(key: jax.Array) -> Level:
        k_size, k_level = jax.random.split(key)
        which = jax.random.randint(k_size, (), 0, len(classes))
        levels = [pad_level(sample_level(k_level, c), classes[-1]) for c in classes]
        # select_n keeps each leaf's dtype (jnp.select would promote the boolean masks to int32, and ~active of
        # an int is not a mask: the physics of such a level is wrong)
        return jax.tree.map(lambda *xs: jax.lax.select_n(which, *xs), *levels)

    return generator
