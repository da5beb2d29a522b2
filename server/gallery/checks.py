"""What a gallery write accepts: the errors callers see (a user-facing message and an HTTP status) and the check of
every field, done before anything touches the database (so nothing is written when one fails)."""

from __future__ import annotations

import dataclasses
import hmac
import re
from typing import Any

SIZES = ("s", "m", "l", "xl")
KINDS = ("human", "agent")
SORTS = ("newest", "top", "played", "hardest")
MAX_NAME = 100
MAX_DESCRIPTION = 2000
MAX_TAGS = 10
TAG_RE = re.compile(r"^[a-z0-9][a-z0-9_-]{0,31}$")
THUMBNAIL_SIZE = 256
ID_RE = re.compile(r"[A-Za-z0-9_-]{1,32}")
RECORDING_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,200}$")  # a plain file name under recordings/


class StoreError(Exception):
    status = 400

    def __init__(self, message: str):
        super().__init__(message)
        self.message = message


class Invalid(StoreError):
    status = 422


class NotFound(StoreError):
    status = 404


class Unauthorized(StoreError):
    status = 401


class Forbidden(StoreError):
    status = 403


@dataclasses.dataclass
class SavedLevel:
    """What a save produces before it touches the database: validated fields and the rendered thumbnail."""

    size: str
    level_json: str
    thumbnail: bytes


def prepare_level(level: Any, name: str | None = None) -> SavedLevel:
    """Validate a level document (either format, as a parsed dict) and render its thumbnail.

    Raises Invalid with the loader's message; the gallery holds levels of size s, m or l only, the classes
    the play server compiles for.
    """
    from kinetix.level import LevelError
    from kinetix.levels import dumps, load_level
    from kinetix.render import render_thumbnail_png

    if not isinstance(level, dict):
        raise Invalid(f"level: expected a JSON object in our format or the Kinetix format, got {_json_type(level)}")
    check_document_text("level", level)
    try:
        file = load_level(level)
    except LevelError as error:
        raise Invalid(f"level: {error}") from None
    except RecursionError:
        raise Invalid("level: nested too deeply") from None
    if file.size.name not in SIZES:
        raise Invalid(f"level: size {file.size.name!r} is not a gallery size class; use s, m, l or xl")
    if name is not None:
        file = dataclasses.replace(file, name=name)
    return SavedLevel(file.size.name, dumps(file, "ours"), render_thumbnail_png(file.level, THUMBNAIL_SIZE))


def _json_type(value: Any) -> str:
    return {dict: "object", list: "array", str: "string", bool: "boolean", int: "number", float: "number",
            type(None): "null"}.get(type(value), type(value).__name__)


def check_unicode(field: str, text: str) -> str:
    """`text` unchanged if both databases can store it: no lone UTF-16 surrogates (JSON's "\\ud800" decodes to
    one, and neither UTF-8 nor PostgreSQL can hold it) and no NUL (PostgreSQL text cannot hold it)."""
    if "\x00" in text:
        raise Invalid(f"{field}: must not contain NUL characters")
    try:
        text.encode("utf-8")
    except UnicodeEncodeError as error:
        raise Invalid(f"{field}: contains a lone UTF-16 surrogate ({text[error.start]!r} at character "
                      f"{error.start}); text must be valid Unicode") from None
    return text


def check_document_text(field: str, value: Any, depth: int = 0) -> None:
    """Every string (keys too) of a parsed JSON document is valid Unicode; the error names the path."""
    if depth > 64:
        raise Invalid(f"{field}: nested too deeply")
    if isinstance(value, str):
        try:
            value.encode("utf-8")
        except UnicodeEncodeError:
            raise Invalid(f"{field}: contains a lone UTF-16 surrogate; text must be valid Unicode") from None
    elif isinstance(value, dict):
        for key, item in value.items():
            path = f"{field}.{str(key).encode('utf-8', 'replace').decode()}"  # printable even if the key is not
            check_document_text(path, key, depth + 1)
            check_document_text(path, item, depth + 1)
    elif isinstance(value, list):
        for i, item in enumerate(value):
            check_document_text(f"{field}[{i}]", item, depth + 1)


def check_name(name: Any) -> str:
    if not isinstance(name, str):
        raise Invalid(f"name: expected a string, got {_json_type(name)}")
    if not name.strip():
        raise Invalid("name: must not be empty")
    if len(name) > MAX_NAME:
        raise Invalid(f"name: {len(name)} characters, at most {MAX_NAME} allowed")
    return check_unicode("name", name)


def check_description(description: Any) -> str:
    if not isinstance(description, str):
        raise Invalid(f"description: expected a string, got {_json_type(description)}")
    if len(description) > MAX_DESCRIPTION:
        raise Invalid(f"description: {len(description)} characters, at most {MAX_DESCRIPTION} allowed")
    return check_unicode("description", description)


def check_tags(tags: Any) -> list[str]:
    if not isinstance(tags, list):
        raise Invalid(f"tags: expected a list of strings, got {_json_type(tags)}")
    if len(tags) > MAX_TAGS:
        raise Invalid(f"tags: {len(tags)} tags, at most {MAX_TAGS} allowed")
    out: list[str] = []
    for i, tag in enumerate(tags):
        if not isinstance(tag, str) or not TAG_RE.match(tag.strip().lower()):
            raise Invalid(f"tags[{i}]: {tag!r} is not a tag: 1-32 of a-z, 0-9, '-', '_', starting with a "
                          "letter or digit")
        if tag.strip().lower() not in out:
            out.append(tag.strip().lower())
    return out


def check_id(level_id: Any) -> str:
    if not isinstance(level_id, str) or not ID_RE.fullmatch(level_id):
        raise NotFound(f"no level with id {str(level_id)[:40]!r}")
    return level_id


def check_admin(token: str | None, admin_token: str | None) -> bool:
    return bool(token and admin_token and hmac.compare_digest(token.encode(), admin_token.encode()))
