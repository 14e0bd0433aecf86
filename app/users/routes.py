from __future__ import annotations

from fastapi import APIRouter, Request, Response

from app.audit import service as audit
from app.deps import (
    SESSION_COOKIE,
    AdminUser,
    ClientIp,
    CtxDep,
    CurrentUser,
    SessionDep,
    token_from,
)
from app.errors import NotAuthenticated
from app.limits import IdPath
from app.users import service
from app.users.schemas import (
    CountOut,
    LoginIn,
    LoginOut,
    PasswordChange,
    PasswordReset,
    SessionOut,
    UserCreate,
    UserListItem,
    UserOut,
    UserPatch,
)

router = APIRouter(prefix="/api", tags=["users"])

# who may call what (checked route by route by tests/app/test_security.py): see app/access.py
ACCESS = {
    "POST /api/auth/login": "public",
    "POST /api/auth/logout": "user",
    "GET /api/auth/me": "user",
    "POST /api/auth/password": "user",
    "GET /api/auth/sessions": "user",
    "DELETE /api/auth/sessions/{tid}": "user",
    "GET /api/users": "admin",
    "POST /api/users": "admin",
    "PATCH /api/users/{uid}": "admin",
    "POST /api/users/{uid}/password": "admin",
    "POST /api/users/{uid}/unlock": "admin",
    "GET /api/users/{uid}/sessions": "admin",
    "DELETE /api/users/{uid}/sessions": "admin",
}


@router.post("/auth/login", response_model=LoginOut,
             responses={401: {"description": "wrong credentials"}, 429: {"description": "throttled"}})
def login(body: LoginIn, request: Request, response: Response, session: SessionDep, ctx: CtxDep,
          ip: ClientIp):
    try:
        user, token = service.login(session=session, settings=ctx.settings, username=body.username,
                                    password=body.password, client_ip=ip,
                                    user_agent=request.headers.get("user-agent"))
    except NotAuthenticated:
        audit.record(session, "login_failed", actor_name=body.username[:64], client_ip=ip)
        raise
    audit.record(session, "login", actor=user, client_ip=ip)
    response.set_cookie(SESSION_COOKIE, token, httponly=True, samesite="lax",
                        secure=request.url.scheme == "https",  # TLS, or a trusted proxy's
                        # X-Forwarded-Proto with `occufly serve --proxy-headers` (app.serving)
                        max_age=ctx.settings.session_seconds, path="/")
    return LoginOut(user=UserOut.model_validate(user), token=token)


@router.post("/auth/logout", status_code=204, response_class=Response)
def logout(request: Request, session: SessionDep, ctx: CtxDep, user: CurrentUser,
           ip: ClientIp) -> Response:
    token = token_from(request)
    if token:
        service.logout(session=session, settings=ctx.settings, token=token)
    audit.record(session, "logout", actor=user, client_ip=ip)
    response = Response(status_code=204)
    response.delete_cookie(SESSION_COOKIE, path="/")
    return response


@router.get("/auth/me", response_model=UserOut)
def me(user: CurrentUser):
    return user


@router.post("/auth/password", response_model=CountOut,
             responses={403: {"description": "the current password is wrong"}})
def change_password(body: PasswordChange, request: Request, session: SessionDep, user: CurrentUser,
                    ip: ClientIp):
    """Change your own password; every other session of yours ends (count = sessions ended)."""
    n = service.change_password(session=session, user=user, current=body.current, new=body.new,
                                keep_session_id=getattr(request.state, "auth_session_id", None))
    audit.record(session, "password_change", actor=user, target=user.username, client_ip=ip,
                 detail={"sessions_revoked": n})
    return {"count": n}


def _sessions_out(rows, current_id: int | None) -> list[dict]:  # noqa: ANN001
    return [dict(id=r.id, created_at=r.created_at, expires_at=r.expires_at,
                 last_seen_at=r.last_seen_at, client_ip=r.client_ip, user_agent=r.user_agent,
                 current=r.id == current_id) for r in rows]


@router.get("/auth/sessions", response_model=list[SessionOut])
def my_sessions(request: Request, session: SessionDep, user: CurrentUser):
    return _sessions_out(service.list_sessions(session=session, user_id=user.id),
                         getattr(request.state, "auth_session_id", None))


@router.delete("/auth/sessions/{tid}", status_code=204, response_class=Response)
def revoke_my_session(tid: IdPath, session: SessionDep, user: CurrentUser, ip: ClientIp) -> Response:
    service.revoke_session(session=session, user_id=user.id, session_id=tid)
    audit.record(session, "session_revoke", actor=user, target=user.username, client_ip=ip,
                 detail={"session": tid})
    return Response(status_code=204)


@router.get("/users", response_model=list[UserListItem])
def list_users(session: SessionDep, _admin: AdminUser):
    return service.list_users(session=session)


@router.post("/users", response_model=UserListItem, status_code=201)
def create_user(body: UserCreate, session: SessionDep, admin: AdminUser, ip: ClientIp):
    user = service.create_user(session=session, username=body.username, password=body.password,
                               role=body.role)
    audit.record(session, "user_create", actor=admin, target=user.username, client_ip=ip,
                 detail={"role": user.role, "user_id": user.id})
    return user


@router.patch("/users/{uid}", response_model=UserListItem)
def update_user(uid: IdPath, body: UserPatch, session: SessionDep, admin: AdminUser, ip: ClientIp):
    """Change a user's role or deactivate/reactivate them (deactivation ends every session)."""
    user = service.get_user(session=session, user_id=uid)
    changes = service.update_user(session=session, actor=admin, user=user, role=body.role,
                                  active=body.active)
    if changes:
        audit.record(session, "user_update", actor=admin, target=user.username, client_ip=ip,
                     detail={"user_id": user.id, **changes})
    return user


@router.post("/users/{uid}/password", response_model=CountOut)
def reset_password(uid: IdPath, body: PasswordReset, session: SessionDep, admin: AdminUser,
                   ip: ClientIp):
    """Set a new password for a user; all of their sessions end (count = sessions ended)."""
    user = service.get_user(session=session, user_id=uid)
    n = service.reset_password(session=session, user=user, new=body.password)
    audit.record(session, "password_reset", actor=admin, target=user.username, client_ip=ip,
                 detail={"user_id": user.id, "sessions_revoked": n})
    return {"count": n}


@router.post("/users/{uid}/unlock", response_model=CountOut)
def unlock_user(uid: IdPath, session: SessionDep, admin: AdminUser, ip: ClientIp):
    """Lift the failed-login locks on an account (count = locks removed)."""
    user = service.get_user(session=session, user_id=uid)
    n = service.unlock(session=session, user=user)
    audit.record(session, "user_unlock", actor=admin, target=user.username, client_ip=ip,
                 detail={"user_id": user.id, "locks_removed": n})
    return {"count": n}


@router.get("/users/{uid}/sessions", response_model=list[SessionOut])
def user_sessions(uid: IdPath, session: SessionDep, _admin: AdminUser):
    user = service.get_user(session=session, user_id=uid)
    return _sessions_out(service.list_sessions(session=session, user_id=user.id), None)


@router.delete("/users/{uid}/sessions", response_model=CountOut)
def revoke_user_sessions(uid: IdPath, session: SessionDep, admin: AdminUser, ip: ClientIp):
    """End every session of a user at once (count = sessions ended)."""
    user = service.get_user(session=session, user_id=uid)
    n = service.revoke_all(session=session, user_id=user.id)
    audit.record(session, "session_revoke", actor=admin, target=user.username, client_ip=ip,
                 detail={"user_id": user.id, "sessions_revoked": n})
    return {"count": n}
