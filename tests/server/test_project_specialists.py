"""The specialists shipped for the project's own levels (server.agents.project): each names a project level in the
editor's own form, loads, and acts on it; a directory without a checkpoint or without its level is not offered."""

import json

import jax
import numpy as np

import jax2d
from kinetix.agents.policy import SPECIALISTS_DIR, load_policy
from kinetix.env import EnvConfig, make_env
from kinetix.formats import build
from kinetix.levels import load_level
from server.agents.project import REPO_LEVELS, ProjectSpecialists
from server.agents.training_tab import without_name
from server.editor import levelio


def test_every_shipped_specialist_has_its_level_loads_and_acts():
    shipped = ProjectSpecialists().available()
    on_disk = {d.name for d in SPECIALISTS_DIR.iterdir() if d.is_dir()} if SPECIALISTS_DIR.is_dir() else set()
    assert set(shipped) == on_disk, "every directory there is a checkpoint for a level of levels/"
    assert "car_right" in shipped  # the level the general agent loses (issue 33)
    for stem, path in shipped.items():
        level = load_level(REPO_LEVELS / f"{stem}.json")
        env = make_env(EnvConfig(level.size.name), level)
        obs, _ = env.reset(jax.random.key(0))
        action, value = jax2d.jit(load_policy(str(path), env).act)(jax.random.key(1), obs)
        assert env.action_space.contains(np.asarray(action)) and np.isfinite(float(value)), stem


def test_every_shipped_specialist_s_level_file_is_what_the_editor_exports_for_it():
    """ProjectSpecialists compares a tab's exported level with the project file as read, so each file must be in the
    editor's own form (our format, as levelio.export writes it): a hand-edited file that is not would never match."""
    for stem in ProjectSpecialists().available():
        path = REPO_LEVELS / f"{stem}.json"
        spec, size = levelio.parse(path.read_bytes(), path.name)
        exported = json.loads(levelio.export(build(spec, size), "ours"))
        assert without_name(exported) == without_name(json.loads(path.read_text())), stem


def test_only_complete_specialists_of_existing_levels_are_offered(tmp_path):
    (tmp_path / "car_right").mkdir()
    (tmp_path / "car_right" / "config.json").write_text("{}")
    (tmp_path / "no_such_level").mkdir()
    (tmp_path / "no_such_level" / "config.json").write_text("{}")
    (tmp_path / "car_ramp").mkdir()  # no checkpoint in it
    project = ProjectSpecialists(tmp_path, REPO_LEVELS)
    assert list(project.available()) == ["car_right"]
    document = json.loads((REPO_LEVELS / "car_ramp.json").read_text())
    assert project.matching(document) == []
