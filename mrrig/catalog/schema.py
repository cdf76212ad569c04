"""The catalog's one table, `runs`, as SQLAlchemy Core sees it. The database's schema is made
and changed only by the migrations (mrrig/catalog/migrations/versions/); this description must
match the newest of them (tests/test_catalog.py compares both)."""

from __future__ import annotations

import sqlalchemy as sa

# the newest migration's revision: a catalog at this revision needs no migration
SCHEMA_REVISION = "0002"

metadata = sa.MetaData()

runs = sa.Table(
    "runs",
    metadata,
    sa.Column("run_id", sa.String(36), primary_key=True),
    sa.Column("rig", sa.String(200), nullable=False),
    sa.Column("host", sa.String(255), nullable=False),
    sa.Column("specimen", sa.String(200)),
    sa.Column("operator", sa.String(200), nullable=False),
    sa.Column("plan", sa.String(200)),
    sa.Column("step", sa.String(200)),
    sa.Column("started_utc", sa.DateTime(), nullable=False),
    sa.Column("ended_utc", sa.DateTime()),
    sa.Column("duration_s", sa.Float()),
    sa.Column("controller", sa.String(100), nullable=False),
    sa.Column("controller_params", sa.JSON(), nullable=False),
    sa.Column("model_path", sa.Text()),
    sa.Column("model_sha256", sa.String(64)),
    sa.Column("config_sha256", sa.String(64)),
    sa.Column("dbc_sha256", sa.String(64)),
    sa.Column("mrrig_version", sa.String(100), nullable=False),
    sa.Column("et", sa.Float()),
    sa.Column("faults_count", sa.Integer(), nullable=False),
    sa.Column("faults", sa.JSON(), nullable=False),
    sa.Column("latency_p50_us", sa.Float()),
    sa.Column("latency_p99_us", sa.Float()),
    sa.Column("peak_current_a", sa.Float()),
    sa.Column("temp_max_degc", sa.Float()),
    sa.Column("verdict", sa.String(100)),
    sa.Column("recording_path", sa.Text()),
    sa.Column("recording_size_bytes", sa.BigInteger()),
    sa.Column("recording_sha256", sa.String(64)),
    sa.Column("tags", sa.JSON(), nullable=False),
    # when this row was last written (UTC): sync brings a newer registration of a run over
    sa.Column("registered_utc", sa.DateTime(), nullable=False),
    # the test campaign the run belongs to (migration 0002: after the columns of 0001)
    sa.Column("campaign", sa.String(200)),
    sa.Index("ix_runs_started_utc", "started_utc"),
    sa.Index("ix_runs_rig", "rig"),
    sa.Index("ix_runs_specimen", "specimen"),
    sa.Index("ix_runs_plan", "plan"),
    sa.Index("ix_runs_controller", "controller"),
    sa.Index("ix_runs_campaign", "campaign"),
)
