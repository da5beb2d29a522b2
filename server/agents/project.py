"""Project specialists: agents shipped with the repository for the project's own levels (levels/).

The general agent plays every level, but on some of the project's levels it does not win yet (car_right, issue
33), and racing the agent is the point of the browser app. So a project level may ship a specialist, fine-tuned
from the general agent, in `kinetix/agents/specialists/<level stem>/` (a checkpoint; its README says how each was
made). A tab is offered it while it shows that level unchanged, however it was opened (the gallery's seeded copy,
a file, a link): the tab's level is compared, as our format's document without its name, with the project
file's. An edited level gets no project specialist: it is no longer the level it was trained on.

The tab's own and the gallery's specialists come first (server.agents.tab.AgentLink.specialists), so "best" picks
a specialist someone trained for the level over the shipped one, and the shipped one over the general agent.
"""

from __future__ import annotations

import json
import logging
import threading
from pathlib import Path

from kinetix.agents.checkpoint import CONFIG_FILE
from kinetix.agents.policy import SPECIALISTS_DIR
from server.agents.training_tab import without_name
from server.gallery.store import REPO_LEVELS

log = logging.getLogger(__name__)


class ProjectSpecialists:
    """The shipped specialists and the project levels they were trained on, matched by level content."""

    def __init__(self, specialists_dir: Path = SPECIALISTS_DIR, levels_dir: Path = REPO_LEVELS):
        self.specialists_dir = Path(specialists_dir)
        self.levels_dir = Path(levels_dir)
        # stem -> (checkpoint dir, the level as the editor exports it, without name); read once per process
        self._known: dict[str, tuple[Path, dict]] | None = None
        self._lock = threading.Lock()

    def available(self) -> dict[str, Path]:
        """{level stem: checkpoint dir} for every shipped specialist whose project level exists."""
        if not self.specialists_dir.is_dir():
            return {}
        return {d.name: d for d in sorted(self.specialists_dir.iterdir())
                if (d / CONFIG_FILE).is_file() and (self.levels_dir / f"{d.name}.json").is_file()}

    def _level_documents(self) -> dict[str, tuple[Path, dict]]:
        """Each shipped specialist with its project level's document without its name, read once per process (the
        shipped files do not change while the server runs). A project file is what the editor exports for it
        (tests/server/test_project_specialists.py checks each), so it is compared as read: parsing, building and
        exporting all 13 took 2 s of Python holding the interpreter lock, which delayed the frames of the tab whose
        agent button first asked for them."""
        with self._lock:
            if self._known is None:
                known = {}
                for stem, checkpoint in self.available().items():
                    path = self.levels_dir / f"{stem}.json"
                    try:
                        known[stem] = (checkpoint, without_name(json.loads(path.read_text())))
                    except (OSError, ValueError):  # a broken project file is a bug in the repository: say so
                        log.exception("project level %s could not be read for its specialist", path)
                self._known = known
            return self._known

    def matching(self, document: dict) -> list[tuple[str, str]]:
        """(label, checkpoint dir) of the shipped specialists trained on exactly this level (our format's
        document of the tab's level)."""
        wanted = without_name(document)
        return [(f"project specialist ({stem})", str(checkpoint))
                for stem, (checkpoint, known) in self._level_documents().items() if known == wanted]
