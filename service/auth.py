"""REST bearer tokens: two scopes (read, admin), kept hashed in the service's database, compared in constant
time, never logged.

A token is `efr_` (read) or `efa_` (admin) plus 43 random URL-safe characters (256 bits), so a plain SHA-256
is the right hash: there is nothing to guess that a slow hash would protect. Every endpoint except /healthz
needs a token (the app-level dependency `authorize`); admin endpoints (the /tokens router) need an admin one.
When the app is built without a TokenAuth (tests, `--insecure` without --admin-token-file), REST is open.
"""

from __future__ import annotations

import errno
import hashlib
import hmac
import os
import re
import secrets
import tempfile
import time
from pathlib import Path
from typing import Annotated, Literal

from fastapi import APIRouter, Depends, HTTPException, Request, Response
from fastapi import Path as PathParam
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from pydantic import BaseModel, Field, field_validator

from .store import Store

SCOPES = ("read", "admin")
# "/" is the fleet page's HTML shell (its data needs a token); /docs and /redoc the API's documentation (no data:
# their openapi.json is open too)
PUBLIC_PATHS = frozenset({"/healthz", "/", "/docs", "/docs/oauth2-redirect", "/redoc"})
PUBLIC_PREFIX = "/static/"  # the page's script, style and Plotly.js: code, no data
_PREFIX = {"read": "efr_", "admin": "efa_"}
# text an operator reads on one line (a terminal, a cell of the fleet page): a newline broke the line, an escape
# sequence reached the terminal, a NUL was stored as U+FFFD on PostgreSQL (and kept on SQLite)
CONTROL_CHARACTERS = re.compile(r"[\x00-\x1f\x7f-\x9f]")
TOKEN_NAME_MAX = 200


def check_token_name(name: str) -> str:
    """A token's name as it is shown (`token list`, and as who acknowledged an alarm or retired a drive): ValueError
    for one that is not a line of text."""
    if CONTROL_CHARACTERS.search(name):
        raise ValueError(
            f"a token's name is one line of text: no control characters (newline, tab, NUL, ESC): {name!r}"
        )
    if len(name) > TOKEN_NAME_MAX:
        raise ValueError(f"a token's name is at most {TOKEN_NAME_MAX} characters, not {len(name)}")
    return name


def shown_name(name: str) -> str:
    """A token's name as it is shown and recorded (`token list`, who acknowledged an alarm or retired a drive):
    escaped when it is not one line of text (a name made before check_token_name), so no escape sequence in it
    reaches an operator's terminal."""
    return ascii(name) if CONTROL_CHARACTERS.search(name) else name


def _digest(token: str) -> str:
    return hashlib.sha256(token.encode("utf-8", errors="replace")).hexdigest()


class TokenAuth:
    """Tokens in the store's database (migration 030_tokens.sql)."""

    def __init__(self, store: Store):
        self.store = store

    def create(self, scope: str, name: str = "") -> tuple[int, str]:
        """(id, token); the token is returned once and only its hash is kept."""
        if scope not in SCOPES:
            raise ValueError(f"scope must be one of {SCOPES}, not {scope!r}")
        check_token_name(name)
        token = _PREFIX[scope] + secrets.token_urlsafe(32)
        with self.store._tx() as c:
            cur = c.execute(
                "INSERT INTO api_tokens (name, scope, token_sha256, created_at) VALUES (?, ?, ?, ?)",
                (name or scope, scope, _digest(token), time.time()),
            )
            return cur.lastrowid, token

    def _live(self, token: str):
        """The live token's row (id, name, scope), or None. Every live token's hash is compared, each in constant
        time."""
        wanted = _digest(token)
        found = None
        for row in self.store._rows("SELECT id, name, scope, token_sha256 FROM api_tokens WHERE revoked_at IS NULL"):
            if hmac.compare_digest(row["token_sha256"], wanted):
                found = row
        return found

    def scope_of(self, token: str) -> str | None:
        """The token's scope, or None."""
        row = self._live(token)
        return None if row is None else row["scope"]

    def tokens(self) -> list[dict]:
        rows = self.store._rows("SELECT id, name, scope, created_at, revoked_at FROM api_tokens ORDER BY id")
        return [dict(r) for r in rows]

    def revoke(self, token_id: int) -> bool:
        with self.store._tx() as c:
            cur = c.execute(
                "UPDATE api_tokens SET revoked_at = ? WHERE id = ? AND revoked_at IS NULL", (time.time(), token_id)
            )
            return cur.rowcount > 0

    def count(self) -> int:
        return self.store._rows("SELECT count(*) AS n FROM api_tokens WHERE revoked_at IS NULL")[0]["n"]

    def first_admin_token(self, path) -> Path | None:
        """At first start (no token yet): an admin token written to `path`, 0600. None if tokens exist."""
        if self.count():
            return None
        token_id, token = self.create("admin", "first admin (written at first start)")
        try:
            write_token_file(path, token)
        except BaseException:
            self.revoke(token_id)  # nobody holds it: the next start writes a first admin token again
            raise
        return Path(path)

    def id_of(self, token: str) -> int | None:
        """The id of the live token `token`, or None."""
        row = self._live(token)
        return None if row is None else row["id"]


def write_token_file(path, token: str, *, replace: bool = True) -> None:
    """`token` as a new 0600 file at `path` (its folder made if need be): a temporary file beside it, 0600 before a
    byte is written, renamed onto the path. Written into a file already there, a token was readable with that file's
    mode until a chmod, and through a symlink it went wherever the link pointed (a security review): a link at the
    path is replaced, never followed. replace=False: anything at the path (a file, a link, a folder) is left as it
    is and FileExistsError raised, checked in the same step as the file is made (O_CREAT | O_EXCL, which a link at
    the path fails too; a hard link, which vfat and some network mounts refuse, is not needed)."""
    path = Path(path)
    if path.is_dir() and not path.is_symlink():
        raise IsADirectoryError(errno.EISDIR, "is a directory, not a file", str(path))
    path.parent.mkdir(parents=True, exist_ok=True)
    if not replace:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
        try:
            with os.fdopen(fd, "w") as out:
                out.write(token + "\n")
                out.flush()
                os.fsync(out.fileno())
        except BaseException:
            path.unlink(missing_ok=True)  # ours, made just now: no half-written token left behind
            raise
        return
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")  # O_EXCL, 0600
    try:
        with os.fdopen(fd, "w") as out:
            out.write(token + "\n")
            out.flush()
            os.fsync(out.fileno())
        os.replace(tmp, path)
    finally:
        Path(tmp).unlink(missing_ok=True)  # renamed: gone already


# --- FastAPI ----------------------------------------------------------------------------------------

bearer = HTTPBearer(auto_error=False, description="A token from `encoder-fleet token create --scope read|admin`.")
Credentials = Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)]


def _unauthorized(detail: str) -> HTTPException:
    return HTTPException(status_code=401, detail=detail, headers={"WWW-Authenticate": "Bearer"})


def authorize(request: Request, credentials: Credentials) -> str | None:
    """App-level dependency: the caller's scope; 401 without a valid token (except the public paths)."""
    auth: TokenAuth | None = getattr(request.app.state, "auth", None)
    route = request.scope.get("route")
    path = getattr(route, "path", request.url.path)
    if auth is None or path in PUBLIC_PATHS or path.startswith(PUBLIC_PREFIX):
        return None
    if credentials is None or credentials.scheme.lower() != "bearer" or not credentials.credentials:
        raise _unauthorized("a bearer token is required (encoder-fleet token create)")
    row = auth._live(credentials.credentials)
    if row is None:
        raise _unauthorized("the token is not valid")
    request.state.scope = row["scope"]
    request.state.token = f"token {row['id']} ({shown_name(row['name'])})"  # who did it, for what a change records
    return row["scope"]


def require_admin(request: Request) -> None:
    if getattr(request.app.state, "auth", None) is not None and getattr(request.state, "scope", None) != "admin":
        raise HTTPException(status_code=403, detail="this endpoint needs an admin token")


class TokenInfo(BaseModel):
    id: int
    name: str
    scope: Literal["read", "admin"]
    created_at: float = Field(description="Service clock, unix s.")
    revoked_at: float | None


class NewToken(BaseModel):
    scope: Literal["read", "admin"]
    name: str = Field("", max_length=TOKEN_NAME_MAX, description="What the token is for (shown in the list).")

    @field_validator("name")
    @classmethod
    def one_line(cls, name: str) -> str:
        return check_token_name(name)


class CreatedToken(TokenInfo):
    token: str = Field(description="Shown once: only its hash is kept.")


tokens = APIRouter(prefix="/tokens", tags=["tokens"], dependencies=[Depends(require_admin)])


def _auth(request: Request) -> TokenAuth:
    return request.app.state.auth


@tokens.get("", response_model=list[TokenInfo], summary="REST tokens (admin): names and scopes, never the tokens")
def list_tokens(request: Request):
    return _auth(request).tokens()


@tokens.post("", response_model=CreatedToken, status_code=201, summary="Create a REST token (admin)")
def create_token(body: NewToken, request: Request):
    auth = _auth(request)
    token_id, token = auth.create(body.scope, body.name)
    info = next(t for t in auth.tokens() if t["id"] == token_id)
    return CreatedToken(**info, token=token)


@tokens.delete(
    "/{token_id}",
    status_code=204,
    response_class=Response,
    responses={404: {"description": "No such live token."}},
    summary="Revoke a REST token (admin)",
)
def revoke_token(token_id: Annotated[int, PathParam(ge=1, le=2**62)], request: Request):
    if not _auth(request).revoke(token_id):
        raise HTTPException(status_code=404, detail=f"no live token {token_id}")
    return Response(status_code=204)
