"""Import, export, new, random and shaken levels in the editor model."""

import json
from pathlib import Path

import pytest

from kinetix.formats import build
from kinetix.levels import load_level
from server.editor import Editor, EditorError
from tests.server.editor.scenes import hinged_editor

REPO = Path(__file__).resolve().parents[3]


@pytest.fixture
def ed() -> Editor:
    editor = hinged_editor()
    editor.selection = [("joint", 0)]
    editor.set_properties(motor_on=True, motor_binding=2, limits_on=True, limit_min=-20.0, limit_max=40.0)
    editor.selection = [("body", 5)]
    editor.set_properties(role="green", restitution=0.5)
    editor.set_gravity(0.0, -7.0)
    return editor


@pytest.mark.parametrize("fmt", ["ours", "kinetix"])
def test_export_import_round_trip(ed, fmt):
    text = ed.export(fmt)
    other = Editor()
    other.import_bytes(text.encode())
    assert other.size == ed.size
    assert other.export(fmt) == text
    assert other.export("ours") == ed.export("ours") if fmt == "ours" else True
    # the same level, entity by entity, whatever order the bodies are stored in
    a, b = ed.level_file().level, other.level_file().level
    assert int(a.sim.bodies.active.sum()) == int(b.sim.bodies.active.sum()) == 6
    assert a.sim.gravity.tolist() == b.sim.gravity.tolist()
    assert other.spec.joints[0].motor_binding == 2 and other.spec.joints[0].limits is not None
    assert not other.can_undo  # opened over the untouched blank level: the opened level is the history's base
    other.import_bytes(text.encode(), "my car.json")
    assert other.spec.name == "my car"  # a file without a name is named after the file
    assert other.can_undo  # opening over an opened level is one undoable step back to it


def test_export_is_valid_json_in_both_formats(ed):
    assert json.loads(ed.export("ours"))["format_version"] == 1
    assert "env_state" in json.loads(ed.export("kinetix"))
    with pytest.raises(EditorError, match="unknown format"):
        ed.export("xml")


@pytest.mark.parametrize(("data", "match"), [
    (b"\xff\xfe", "not UTF-8"),
    (b"{not json", "not valid JSON"),
    (b"[1, 2]", "not a level file"),
    (b'{"format_version": 1, "bodies": "many"}', "bodies"),
    (b'{"env_state": {}}', "upload"),
])
def test_bad_import_leaves_level_untouched(ed, data, match):
    before, revision, steps = ed.export("ours"), ed.revision, len(ed.history.undo_stack)
    with pytest.raises(EditorError, match=match):
        ed.import_bytes(data)
    assert ed.export("ours") == before and ed.revision == revision and len(ed.history.undo_stack) == steps


def test_import_non_convex_polygon_names_the_field(ed):
    doc = json.loads(ed.export("ours"))
    poly = next(b for b in doc["bodies"] if b["shape"] == "polygon" and not b.get("fixed"))
    poly["vertices"] = [[0, 0], [1, 0], [0.2, 0.2], [0, 1]]
    with pytest.raises(EditorError, match=r"bodies\[\d+\]\.vertices"):
        ed.import_bytes(json.dumps(doc).encode(), "bad.json")


def test_import_project_level():
    ed = Editor()
    path = sorted((REPO / "levels").glob("*.json"))[0]
    ed.import_bytes(path.read_bytes(), path.name)
    assert len(ed.spec.bodies) == int(load_level(path).level.sim.bodies.active.sum()) > 4


def test_import_public_level(shared_dir):
    ed = Editor()
    public = sorted((shared_dir / "kinetix-levels" / "l").glob("*.json"))[0]
    ed.import_bytes(public.read_bytes(), public.name)
    assert ed.size.name == "l"
    expected = load_level(public)
    assert int(ed.level_file().level.sim.bodies.active.sum()) == int(expected.level.sim.bodies.active.sum())


def test_polygon_of_five_vertices_exports_to_kinetix_split_with_a_summary(ed):
    ed.set_tool("polygon")
    for p in [(3.0, 3.0), (4.0, 3.0), (4.5, 3.5), (4.0, 4.0), (3.0, 4.0)]:
        ed.click(*p)
    ed.key("Enter")
    data = json.loads(ed.export("kinetix"))
    assert data["static_env_params"]["max_polygon_vertices"] == 4
    assert sorted(e["n_vertices"] for e in data["env_state"]["polygon"] if e["active"])[:2] == [3, 4]
    (summary,) = ed.export_notes("kinetix")
    assert summary == "split 1 polygon (5 vertices) into 2 parts welded by 1 fixed joint; exported as size l"
    assert ed.export_notes("ours") == []
    other = Editor()
    other.import_bytes(ed.export("kinetix").encode())
    counts = lambda spec: sorted(len(b.vertices or ()) for b in spec.bodies)  # noqa: E731
    assert counts(other.spec) == sorted(counts(ed.spec)[:-1] + [3, 4])  # the pentagon as a triangle and a quad
    assert len(other.spec.joints) == len(ed.spec.joints) + 1


def test_opening_a_level_in_a_fresh_editor_is_its_base_and_undo_keeps_it():
    ed = Editor()
    ed.import_bytes(sorted((REPO / "levels").glob("*.json"))[0].read_bytes())
    opened = ed.export("ours")
    assert not ed.can_undo
    ed.undo()  # Ctrl+Z right after opening: nothing to undo, the opened level stays
    assert ed.export("ours") == opened
    ed.set_gravity(0.0, -5.0)
    ed.undo()
    assert ed.export("ours") == opened


def test_new_level(ed):
    ed.new_level("s")
    assert len(ed.spec.bodies) == 4 and ed.size.name == "s" and ed.selection == []
    ed.undo()
    assert len(ed.spec.bodies) == 6 and ed.size.name == "l"


def test_editor_from_level_file_and_spec():
    file = load_level(REPO / "levels" / sorted(p.name for p in (REPO / "levels").glob("*.json"))[0])
    ed = Editor(file)
    assert ed.size == file.size and len(ed.spec.bodies) == int(file.level.sim.bodies.active.sum())
    again = Editor(ed.spec)
    assert again.export("ours") == ed.export("ours")


# ---------------------------------------------------------------- JAX programs (compiled once per session)


@pytest.fixture(scope="session")
def random_editor() -> Editor:
    ed = Editor(size="m")
    ed.random_level(seed=3)
    return ed


def test_random_level_builds(random_editor):
    ed = random_editor
    assert ed.size.name == "m" and len(ed.spec.bodies) > 4
    build(ed.spec, ed.size)
    assert any(b.role == 1 for b in ed.spec.bodies) and any(b.role == 2 for b in ed.spec.bodies)
    other = Editor(size="m")
    other.random_level(seed=3)
    assert other.export("ours") == ed.export("ours")  # seeded


def test_shake_it_up_changes_and_stays_valid(random_editor):
    ed = Editor(random_editor.level_file())
    before = ed.export("ours")
    changed = False
    for seed in range(4):
        message = ed.shake_it_up(seed)
        build(ed.spec, ed.size)
        changed |= message is None
    assert changed and ed.export("ours") != before
    while ed.undo():
        pass
    assert ed.export("ours") == before
