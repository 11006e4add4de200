"""The database of a test's own Prefect server: PostgreSQL when LATENT_STEERING_TEST_POSTGRES names one, else SQLite.

`.ci/run` starts a PostgreSQL server (`.ci/postgres`, Debian's package) and exports its URL
(`postgresql+asyncpg://user:password@host:port/database`): each test server then gets a database of its own, made
from that URL and dropped afterwards, as a fleet's server would (deployments/README.md, "A fleet"). Without the
variable (a developer's `uv run pytest -q`) each server keeps Prefect's default, SQLite in its PREFECT_HOME.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import uuid
from collections.abc import Iterator

POSTGRES_ENV = "LATENT_STEERING_TEST_POSTGRES"
URL_SCHEME = "postgresql+asyncpg://"


def backend() -> str:
    """Name the database the test servers use, for the test report."""
    url = os.environ.get(POSTGRES_ENV)
    return f"PostgreSQL ({url.rsplit('@', 1)[-1]})" if url else f"SQLite (set {POSTGRES_ENV} for PostgreSQL)"


@contextlib.contextmanager
def server_database() -> Iterator[dict[str, str]]:
    """Yield the environment a Prefect server needs for a database of its own: a new PostgreSQL database (dropped at
    the end) or nothing (SQLite)."""
    url = os.environ.get(POSTGRES_ENV)
    if not url:
        yield {}
        return
    if not url.startswith(URL_SCHEME) or "\n" in url:
        raise ValueError(f"{POSTGRES_ENV}: expected one URL {URL_SCHEME}user:password@host:port/database, got {url!r}")
    name = f"prefect_test_{uuid.uuid4().hex[:16]}"
    asyncio.run(_execute(url, f'CREATE DATABASE "{name}"'))
    try:
        yield {"PREFECT_API_DATABASE_CONNECTION_URL": f"{url.rsplit('/', 1)[0]}/{name}"}
    finally:
        asyncio.run(_drop(url, name))


DROP_TRIES = 30  # one a second: an autovacuum worker on the database lasts a moment


async def _drop(url: str, name: str) -> None:
    """Drop the database, its sessions ended (FORCE). An autovacuum worker on it can only be ended by a member of
    pg_signal_backend (`.ci/postgres` grants it): without that, wait for the worker to finish and try again."""
    import asyncpg

    for tries_left in reversed(range(DROP_TRIES)):
        try:
            return await _execute(url, f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')
        except (asyncpg.InsufficientPrivilegeError, asyncpg.ObjectInUseError):
            if not tries_left:
                raise
            await asyncio.sleep(1)


async def _execute(url: str, statement: str) -> None:
    import asyncpg  # only where PostgreSQL is used

    connection = await asyncpg.connect(url.replace(URL_SCHEME, "postgresql://", 1))
    try:
        await connection.execute(statement)
    finally:
        await connection.close()
