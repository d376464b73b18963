"""`encoder-fleet token`: REST bearer tokens in the service's database (service/auth.py)."""

from __future__ import annotations

import os
import stat
from pathlib import Path

from encoder_core.samples import InputError

TAKEN = (
    "already exists (the token it may hold would stay live with nobody holding it): choose another file, "
    "or pass --force to replace it (a live token of this database in it is revoked)"
)


def cmd_token(args) -> int:
    from service.auth import TokenAuth, check_token_name, shown_name, write_token_file
    from service.store import Store

    if args.token_command == "create":
        try:
            check_token_name(args.name or "")
        except ValueError as exc:  # before the database is opened or a file written
            raise InputError(f"--name: {exc}") from None
    if getattr(args, "create_db", False):
        Path(args.db).parent.mkdir(parents=True, exist_ok=True)
    elif not Path(args.db).exists():
        raise InputError(f"--db {args.db}: no such database (start the service once, or give its --db)")
    store = Store.open(args.db)
    try:
        auth = TokenAuth(store)
        if args.token_command == "create":
            out = Path(args.out) if args.out else None
            replacing, held = _at_out(auth, out, args.force) if out is not None else (False, None)
            token_id, token = auth.create(args.scope, args.name or "")
            if out is not None:
                try:
                    write_token_file(out, token, replace=args.force)
                except BaseException as exc:  # a token nobody holds must not stay live: revoked, and the error said
                    try:
                        auth.revoke(token_id)
                    except Exception:
                        raise InputError(
                            f"--out {args.out}: {exc}; token {token_id} could not be revoked either: "
                            f"run `encoder-fleet token revoke {token_id} --db {args.db}`"
                        ) from None
                    if isinstance(exc, FileExistsError):  # a file took the name meanwhile: left as it is
                        raise InputError(f"--out {args.out}: {TAKEN}") from None
                    raise
                said = f"token {token_id} ({args.scope}) written to {args.out} (0600)"
                if replacing and held is None:
                    said += ", replacing the file there (it held no live token of this database)"
                elif replacing:  # the new token is in place: the one nobody holds any more goes now
                    try:
                        auth.revoke(held)
                    except Exception as exc:
                        raise InputError(
                            f"{said}, but token {held}, which the file there held, could not be revoked ({exc}): "
                            f"run `encoder-fleet token revoke {held} --db {args.db}`"
                        ) from None
                    said += f", replacing the file there; token {held}, which it held, is revoked"
                print(said, flush=True)
            else:
                print(token)  # stdout only, once: the database keeps its hash
                print(f"token {token_id} ({args.scope}) created; it is shown once, keep it safe", flush=True)
        elif args.token_command == "list":
            for t in auth.tokens():
                state = "revoked" if t["revoked_at"] else "live"
                print(f"{t['id']:>4} {t['scope']:<6} {state:<8} {shown_name(t['name'])}")
        elif args.token_command == "revoke":
            if not auth.revoke(args.id):
                raise InputError(f"no live token {args.id}")
            print(f"token {args.id} revoked")
    finally:
        store.close()
    return 0


def _at_out(auth, out: Path, force: bool) -> tuple[bool, int | None]:
    """(a file stands at --out, the id of the live token of this database it holds). Refused: a link (a token is
    never written through one, nor over one: over /dev/stdout, --force replaced the system's link), a stream or a
    device, and without --force any file (overwritten, the token in it stayed live with nobody holding it). A folder
    is left to the write to refuse."""
    if not os.path.lexists(out) or (out.is_dir() and not out.is_symlink()):
        return False, None
    if out.is_symlink():
        raise InputError(f"--out {out}: a symbolic link; give the path of a file of its own")
    if not out.is_file():
        raise InputError(f"--out {out}: not a regular file (leave out --out to print the token)")
    if not force:
        raise InputError(f"--out {out}: {TAKEN}")
    # read as checked: a link or a FIFO put there since the checks above is not followed, nor waited on
    fd = os.open(out, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    with os.fdopen(fd, "rb") as f:
        if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
            raise InputError(f"--out {out}: not a regular file (leave out --out to print the token)")
        text = f.read(4096).decode("utf-8", errors="replace").strip()  # a token is 47 characters
    return True, auth.id_of(text) if text else None


def register(sub) -> None:
    p = sub.add_parser("token", help="REST bearer tokens (read, admin) in the service's database")
    tsub = p.add_subparsers(dest="token_command", required=True)
    q = tsub.add_parser("create", help="a new token, printed once (only its hash is stored)")
    q.add_argument("--scope", choices=["read", "admin"], required=True, help="read: every GET; admin: also /tokens")
    q.add_argument("--name", help="what the token is for")
    q.add_argument("--db", default="out/fleet.sqlite", help="the service's database")
    q.add_argument("--out", metavar="FILE", help="write the token to FILE (0600) instead of stdout")
    q.add_argument("--force", action="store_true", help="replace a file at --out (the live token it holds is revoked)")
    q.add_argument("--create-db", action="store_true", help="create the database if it does not exist yet")
    q = tsub.add_parser("list", help="tokens: id, scope, state, name (never the token)")
    q.add_argument("--db", default="out/fleet.sqlite", help="the service's database")
    q = tsub.add_parser("revoke", help="revoke a token by id")
    q.add_argument("id", type=int, help="the token's id (token list)")
    q.add_argument("--db", default="out/fleet.sqlite", help="the service's database")
    p.set_defaults(func=cmd_token)
