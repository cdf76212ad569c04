"""Alembic's environment: the connection comes from `mrrig.catalog.store` (no alembic.ini, no
URL of its own), so a migration runs inside the caller's transaction and lock."""

from __future__ import annotations

from alembic import context

connection = context.config.attributes["connection"]
# SQLite changes a table by copying it (batch mode); PostgreSQL alters it in place
context.configure(connection=connection, render_as_batch=connection.dialect.name == "sqlite")
with context.begin_transaction():
    context.run_migrations()
