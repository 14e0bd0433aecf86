"""scene ids are never reused (issue 36)

Revision ID: 0012
Revises: 0011
Create Date: 2026-12-11 10:00:00

SQLite gives a new row max(id) + 1, so after the newest scene's deletion the next scene got
its id and the audit log mixed two scenes. PostgreSQL's sequence never goes back. Turning the
SQLite table into AUTOINCREMENT needs a rebuild of ``scenes``, whose drop would cascade to
every frame with foreign keys on; instead ``id_counters`` keeps the last scene id handed out
(app.scenes.service.create_scene takes the next one in its transaction on SQLite). Seeded with
the highest scene id any table, the audit log included, has seen.
"""
from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = '0012'
down_revision = '0011'
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        'id_counters',
        sa.Column('name', sa.String(length=32), nullable=False),
        sa.Column('last_id', sa.Integer(), nullable=False),
        sa.PrimaryKeyConstraint('name', name=op.f('pk_id_counters')),
    )
    op.execute(
        "INSERT INTO id_counters (name, last_id) SELECT 'scenes', COALESCE(MAX(i), 0) FROM ("
        "SELECT MAX(id) AS i FROM scenes UNION ALL SELECT MAX(scene_id) FROM audit_events "
        "UNION ALL SELECT MAX(scene_id) FROM jobs) AS seen")


def downgrade() -> None:
    op.drop_table('id_counters')
