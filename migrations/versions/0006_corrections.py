"""label corrections: the override layer, proposals, notifications

Revision ID: 0006
Revises: 0005
Create Date: 2026-12-03 07:30:00

(Reserved in the chain for issue 25 (corrections); a no-op until that work needs a schema change.)
"""
from __future__ import annotations

import sqlalchemy as sa  # noqa: F401
from alembic import op  # noqa: F401

revision = '0006'
down_revision = '0005'
branch_labels = None
depends_on = None


def upgrade() -> None:
    pass


def downgrade() -> None:
    pass
