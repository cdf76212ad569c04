"""A run's campaign: the name that groups the runs of one test campaign (a plan's steps, a
characterization matrix), for `mrrig runs --campaign`.

Revision ID: 0002
Revises: 0001
Create Date: 2026-12-06
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column("runs", sa.Column("campaign", sa.String(200)))
    op.create_index("ix_runs_campaign", "runs", ["campaign"])


def downgrade() -> None:
    op.drop_index("ix_runs_campaign", "runs")
    op.drop_column("runs", "campaign")
