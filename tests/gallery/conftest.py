"""Gallery test fixtures: a fresh store on SQLite always and on PostgreSQL when KINETIX_TEST_POSTGRES_URL is set
(.ci/setup-postgres.sh); in CI (CI=true) a missing PostgreSQL fails instead of skipping."""

from __future__ import annotations

import json
import os
import secrets
from pathlib import Path

import pytest

from server.gallery.store import REPO_LEVELS, Store

ADMIN = "admin-secret-for-tests"


def postgres_url() -> str | None:
    url = os.environ.get("KINETIX_TEST_POSTGRES_URL")
    if not url:
        if os.environ.get("CI") == "true":
            pytest.fail("CI=true but KINETIX_TEST_POSTGRES_URL is not set: .ci/setup-postgres.sh did not start "
                        "PostgreSQL")
        pytest.skip("PostgreSQL tests need KINETIX_TEST_POSTGRES_URL (source .ci/setup-postgres.sh)")
    return url


@pytest.fixture
def pg_schema_url():
    """A SQLAlchemy URL whose connections use a fresh, empty PostgreSQL schema (dropped afterwards)."""
    import sqlalchemy

    url = postgres_url().replace("postgresql://", "postgresql+psycopg://", 1)
    schema = "t_" + secrets.token_hex(6)
    admin = sqlalchemy.create_engine(url, isolation_level="AUTOCOMMIT")
    with admin.connect() as conn:
        conn.exec_driver_sql(f"CREATE SCHEMA {schema}")
    sep = "&" if "?" in url else "?"
    yield f"{url}{sep}options=-csearch_path%3D{schema}"
    with admin.connect() as conn:
        conn.exec_driver_sql(f"DROP SCHEMA {schema} CASCADE")
    admin.dispose()


@pytest.fixture(params=["sqlite", "postgresql"])
def db_url(request, tmp_path: Path) -> str:
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'gallery.sqlite3'}"
    return request.getfixturevalue("pg_schema_url")


@pytest.fixture
def store(db_url: str):
    s = Store(db_url, seed_dir=None)
    yield s
    s.close()


@pytest.fixture
def two(db_url: str):
    """Two stores on one database: what two server processes see."""
    first, second = Store(db_url, seed_dir=None), Store(db_url, seed_dir=None)
    yield first, second
    first.close()
    second.close()


@pytest.fixture
def client(store: Store):
    from fastapi.testclient import TestClient

    from server.gallery.app import create_gallery_app

    with TestClient(create_gallery_app(store, admin_token=ADMIN), base_url="http://localhost") as c:
        yield c


def level_doc(name: str = "car_right") -> dict:
    return json.loads((REPO_LEVELS / f"{name}.json").read_text())
