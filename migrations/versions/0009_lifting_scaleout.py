"""lifting scale-out: worker ownership

Revision ID: 0009
Revises: 0008
Create Date: 2026-12-03 07:30:00

(Reserved in the chain for issue 29 (lifting); a no-op until that work needs a schema change.)
"""
from __future__ import annotations

import sqlalchemy as sa  # noqa: F401
from alembic import op  # noqa: F401

revision = '0009'
down_revision = '0008'
branch_labels = None
depends_on = None


def upgrade() -> None:
    pass


def downgrade() -> None:
    pass
