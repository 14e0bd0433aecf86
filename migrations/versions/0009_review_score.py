"""independent review (issue 23): the review list's ranking score

Revision ID: 0009
Revises: 0008
Create Date: 2026-12-03 13:20:00

frames.review_score: the ranking score of the frame's mask (occufly.lifting.loo.review_score:
the share of the confidently, independently labelled area the mask does not reproduce, plus
the shift test's gain); the review list sorts by it, highest first.
"""
from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0009'
down_revision = '0008'
branch_labels = None
depends_on = None


def upgrade() -> None:
    # NULL until the next labels_updated recomputes the frame's agreement
    with op.batch_alter_table("frames") as b:
        b.add_column(sa.Column("review_score", sa.Float(), nullable=True))


def downgrade() -> None:
    # SQLite rebuilds the table: reflect it alone (see 0004)
    with op.batch_alter_table("frames", reflect_kwargs={"resolve_fks": False}) as b:
        b.drop_column("review_score")
