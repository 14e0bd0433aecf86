from __future__ import annotations

from datetime import datetime
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from app.limits import line

Role = Literal["annotator", "reviewer", "admin"]
Password = line(1024, 1)
NewPassword = line(1024, 8)


class UserOut(BaseModel):
    model_config = ConfigDict(from_attributes=True)
    id: int
    username: str
    role: str


class UserListItem(UserOut):
    created_at: datetime
    active: bool = True


class LoginIn(BaseModel):
    username: line(64, 1)
    password: Password


class LoginOut(BaseModel):
    user: UserOut
    token: str


class UserCreate(BaseModel):
    username: str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.@-]+$")
    password: NewPassword
    role: Role


class UserPatch(BaseModel):
    role: Role | None = None
    active: bool | None = None


class PasswordChange(BaseModel):
    current: Password
    new: NewPassword


class PasswordReset(BaseModel):
    password: NewPassword


class SessionOut(BaseModel):
    id: int
    created_at: datetime
    expires_at: datetime
    last_seen_at: datetime | None
    client_ip: str | None
    user_agent: str | None
    current: bool = False


class CountOut(BaseModel):
    count: int
