"""review: leave-one-out agreement, suspects

Revision ID: 0007
Revises: 0006
Create Date: 2026-12-03 07:30:00

frames: self_agreement, independent_coverage, painted_share (issue 23).
"""
from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0007'
down_revision = '0006'
branch_labels = None
depends_on = None


_COLUMNS = ("self_agreement", "independent_coverage", "painted_share")


def upgrade() -> None:
    # frames.agreement becomes the leave-one-out agreement (recomputed on the next
    # labels_updated); the old self-agreement and the figures beside it get columns
    with op.batch_alter_table("frames") as b:
        for name in _COLUMNS:
            b.add_column(sa.Column(name, sa.Float(), nullable=True))
    op.execute("UPDATE frames SET agreement = NULL")


def downgrade() -> None:
    # SQLite rebuilds the table: reflect it alone (the users table its foreign keys name has
    # an expression index that cannot be reflected: SAWarning)
    with op.batch_alter_table("frames", reflect_kwargs={"resolve_fks": False}) as b:
        for name in reversed(_COLUMNS):
            b.drop_column(name)
