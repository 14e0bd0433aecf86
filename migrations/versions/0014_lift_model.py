"""how a scene's votes are decided: one model for all painters or one per mask author (issue 37)

Revision ID: 0014
Revises: 0013
Create Date: 2026-12-07 17:00:00

``lift_status.model``: the annotator model of the scene's live lifting (app/lifting/models.py
``LIFT_MODELS``): ``pooled`` (one confusion matrix for every painter, the default and what
every scene had before) or ``per_author`` (a confusion matrix per mask author). Set by an
admin (``PUT /api/scenes/{id}/lifting``).
"""
from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0014'
down_revision = '0013'
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table('lift_status') as b:
        b.add_column(sa.Column('model', sa.String(length=16), nullable=False,
                               server_default='pooled'))


def downgrade() -> None:
    with op.batch_alter_table('lift_status') as b:
        b.drop_column('model')
