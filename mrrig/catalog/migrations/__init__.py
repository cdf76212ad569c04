"""Alembic migrations of the catalog, run by `mrrig.catalog.store` when a catalog is opened."""
