"""`encoder-fleet token`: REST bearer tokens in the service's database (service/auth.py)."""

from __future__ import annotations

from pathlib import Path

from encoder_core.samples import InputError
from encoder_fleet.outputs import write_file


def cmd_token(args) -> int:
    from service.auth import TokenAuth
    from service.store import Store

    if getattr(args, "create_db", False):
        Path(args.db).parent.mkdir(parents=True, exist_ok=True)
    elif not Path(args.db).exists():
        raise InputError(f"--db {args.db}: no such database (start the service once, or give its --db)")
    store = Store.open(args.db)
    try:
        auth = TokenAuth(store)
        if args.token_command == "create":
            token_id, token = auth.create(args.scope, args.name or "")
            if args.out:
                try:
                    write_secret(Path(args.out), token)
                except BaseException as exc:  # a token nobody holds must not stay live: revoked, and the error said
                    try:
                        auth.revoke(token_id)
                    except Exception:
                        raise InputError(
                            f"--out {args.out}: {exc}; token {token_id} could not be revoked either: "
                            f"run `encoder-fleet token revoke {token_id} --db {args.db}`"
                        ) from None
                    raise
                print(f"token {token_id} ({args.scope}) written to {args.out} (0600)", flush=True)
            else:
                print(token)  # stdout only, once: the database keeps its hash
                print(f"token {token_id} ({args.scope}) created; it is shown once, keep it safe", flush=True)
        elif args.token_command == "list":
            for t in auth.tokens():
                state = "revoked" if t["revoked_at"] else "live"
                print(f"{t['id']:>4} {t['scope']:<6} {state:<8} {t['name']}")
        elif args.token_command == "revoke":
            if not auth.revoke(args.id):
                raise InputError(f"no live token {args.id}")
            print(f"token {args.id} revoked")
    finally:
        store.close()
    return 0


def write_secret(path: Path, text: str) -> None:
    write_file(path, text + "\n", perms=0o600)


def register(sub) -> None:
    p = sub.add_parser("token", help="REST bearer tokens (read, admin) in the service's database")
    tsub = p.add_subparsers(dest="token_command", required=True)
    q = tsub.add_parser("create", help="a new token, printed once (only its hash is stored)")
    q.add_argument("--scope", choices=["read", "admin"], required=True, help="read: every GET; admin: also /tokens")
    q.add_argument("--name", help="what the token is for")
    q.add_argument("--db", default="out/fleet.sqlite", help="the service's database")
    q.add_argument("--out", metavar="FILE", help="write the token to FILE (0600) instead of stdout")
    q.add_argument("--create-db", action="store_true", help="create the database if it does not exist yet")
    q = tsub.add_parser("list", help="tokens: id, scope, state, name (never the token)")
    q.add_argument("--db", default="out/fleet.sqlite", help="the service's database")
    q = tsub.add_parser("revoke", help="revoke a token by id")
    q.add_argument("id", type=int, help="the token's id (token list)")
    q.add_argument("--db", default="out/fleet.sqlite", help="the service's database")
    p.set_defaults(func=cmd_token)
