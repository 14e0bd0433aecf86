"""Notifications: what a user should see -- a frame of theirs rejected, commented on,
corrected by a reviewer, a proposal filed or declined. Any domain tells people through
:func:`app.notifications.service.notify` / :func:`~app.notifications.service.notify_frame_people`
(in the caller's transaction); the user reads them at ``GET /api/notifications``."""
