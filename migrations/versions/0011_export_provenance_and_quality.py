"""export provenance and quality (issue 23): reserved revision (empty until that work needs a schema change)

Revision ID: 0011
Revises: 0010
Create Date: 2026-12-03 13:20:00
"""
from __future__ import annotations

import sqlalchemy as sa  # noqa: F401
from alembic import op  # noqa: F401

revision = '0011'
down_revision = '0010'
branch_labels = None
depends_on = None


def upgrade() -> None:
    pass


def downgrade() -> None:
    pass
