"""The runs table: one row per run, keyed by its run id (UUID).

Revision ID: 0001
Revises:
Create Date: 2026-12-04
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0001"
down_revision = None
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "runs",
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
        sa.Column("registered_utc", sa.DateTime(), nullable=False),
    )
    for column in ("started_utc", "rig", "specimen", "plan", "controller"):
        op.create_index(f"ix_runs_{column}", "runs", [column])


def downgrade() -> None:
    op.drop_table("runs")
