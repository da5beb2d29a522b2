"""kinetix.level_source: what `--level` (kinetix train) and `level=` (kinetix.gym) name."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from kinetix.level import WALLS_SOLVER, LevelError
from kinetix.level_source import RANDOM_DENSE_REWARD, level_source

LEVELS = Path(__file__).resolve().parents[2] / "levels"


def _copy(src: Path, dst: Path, **env) -> None:
    data = json.loads(src.read_text())
    data["env"].update(env)
    dst.write_text(json.dumps(data))


def test_random_levels_generate_with_static_walls_and_shaping():
    source = level_source("random-m")
    assert source.random and source.size.name == "m" and source.solver == WALLS_SOLVER
    assert source.params.dense_reward_scale == RANDOM_DENSE_REWARD
    assert level_source("random-s", dense_reward=0.0).params.dense_reward_scale == 0.0


def test_a_directory_is_brought_to_its_largest_size_and_keeps_each_levels_params(tmp_path):
    _copy(LEVELS / "thrust_hop.json", tmp_path / "a.json", max_timesteps=40)  # size s
    _copy(LEVELS / "car_right.json", tmp_path / "b.json", max_timesteps=90)  # size m
    source = level_source(tmp_path)
    assert source.size.name == "m" and source.names == ("a", "b")
    assert {lf.size.name for lf in source.files} == {"m"}
    assert np.asarray(source.level_params.max_timesteps).tolist() == [40, 90]
    assert int(source.params.max_timesteps) == 40  # the first level's, as kinetix train uses
    assert np.asarray(level_source(tmp_path, dense_reward=0.5).level_params.dense_reward_scale).tolist() == [0.5, 0.5]
    assert not source.random and source.stacked.sim.bodies.active.shape[0] == 2


def test_bad_specs_are_refused_with_a_reason(tmp_path):
    with pytest.raises(LevelError, match="does not exist"):
        level_source(tmp_path / "nothing.json")
    with pytest.raises(LevelError, match=r"no \*\.json"):
        level_source(tmp_path)
    _copy(LEVELS / "thrust_hop.json", tmp_path / "a.json", frame_skip=2)
    _copy(LEVELS / "thrust_hop.json", tmp_path / "b.json", frame_skip=3)
    with pytest.raises(LevelError, match="different frame skips"):
        level_source(tmp_path)


def test_held_out_generated_levels_are_the_same_each_time():
    import jax

    from kinetix.env import EnvParams
    from kinetix.level_source import eval_levels, held_out_levels

    first = held_out_levels("generated-s", count=3)
    again = held_out_levels("generated-s", count=3)
    assert [name for name, _ in first] == ["generated-s/00", "generated-s/01", "generated-s/02"]
    assert {lf.size.name for _, lf in first} == {"s"}
    assert first[0][1].params.dense_reward_scale == RANDOM_DENSE_REWARD
    for (_, a), (_, b) in zip(first, again, strict=True):
        jax.tree.map(np.testing.assert_array_equal, a.level, b.level)
    assert not np.array_equal(np.asarray(first[0][1].level.sim.bodies.position),
                              np.asarray(first[1][1].level.sim.bodies.position))
    assert EnvParams.from_level_params(first[0][1].params).dense_reward_scale == RANDOM_DENSE_REWARD
    with pytest.raises(LevelError, match="is not one of generated-s"):
        held_out_levels("generated-xl")
    with pytest.raises(LevelError, match="does not exist"):
        eval_levels("generated-xl")  # not a held-out set, so a path, and there is none
