"""Every ORM model, imported in one place (Alembic's ``target_metadata``)."""

from app.annotations.models import MaskVersion
from app.audit.models import AuditEvent
from app.blobs import MaskBlob
from app.corrections.models import CorrectionEdit, MaskProposal
from app.db import Base
from app.jobs.models import Job
from app.lifting.models import Event, LiftQueueEntry, LiftStatus
from app.notifications.models import Notification
from app.review.models import ReviewComment, ReviewItem, SuspectMark
from app.scenes.models import Frame, Scene, SceneMember
from app.shared_limits import ViewerSocket
from app.users.models import AuthToken, LoginThrottle, User

metadata = Base.metadata

__all__ = ["AuditEvent", "CorrectionEdit", "MaskProposal", "Notification", "AuthToken", "Event", "Frame", "Job", "LiftQueueEntry", "LiftStatus",
           "LoginThrottle", "MaskBlob", "MaskVersion",
           "ReviewComment", "ReviewItem", "Scene", "SuspectMark", "SceneMember", "User", "ViewerSocket",
           "metadata"]
