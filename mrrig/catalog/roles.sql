-- The roles of a lab's shared run catalog on PostgreSQL (README, "Run catalog"): observers
-- read, rigs register runs (insert, and update a run registered again or synced from a
-- rig's spool), nobody but the catalog's owner deletes or changes the schema.
--
-- Once, as the owner of the catalog's database, after the schema exists (any mrrig command
-- run with the owner's URL creates it, e.g. `mrrig runs --catalog postgresql://owner@host/db`):
--
--     psql -d mrrig -f mrrig/catalog/roles.sql
--
-- then one login per rig and per desk, in its role:
--
--     CREATE ROLE rig1 LOGIN PASSWORD '...' IN ROLE mrrig_rig;
--     CREATE ROLE alice LOGIN PASSWORD '...' IN ROLE mrrig_observer;

DO $$
BEGIN
    IF NOT EXISTS (SELECT FROM pg_roles WHERE rolname = 'mrrig_observer') THEN
        CREATE ROLE mrrig_observer NOLOGIN;
    END IF;
    IF NOT EXISTS (SELECT FROM pg_roles WHERE rolname = 'mrrig_rig') THEN
        CREATE ROLE mrrig_rig NOLOGIN;
    END IF;
END
$$;

GRANT USAGE ON SCHEMA public TO mrrig_observer, mrrig_rig;
-- opening a catalog reads its schema revision
GRANT SELECT ON alembic_version TO mrrig_observer, mrrig_rig;
GRANT SELECT ON runs TO mrrig_observer;
-- INSERT ... ON CONFLICT (run_id) DO UPDATE: a run registered again replaces its row
GRANT SELECT, INSERT, UPDATE ON runs TO mrrig_rig;
