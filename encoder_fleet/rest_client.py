"""A REST call to the service, as the operator's commands make it (`rollout`, `alarms`, `status`): one line for any
failure, with the service's own reason."""

from __future__ import annotations

import json
import sys
import urllib.error
import urllib.parse
import urllib.request
from pathlib import Path

from encoder_core.samples import InputError
from encoder_fleet.outputs import is_stdout


def add_rest_options(q) -> None:
    q.add_argument("--url", default="http://127.0.0.1:8000", help="the service's REST address")
    q.add_argument("--token-file", metavar="FILE", help="a REST token (admin to change anything)")
    q.add_argument("--json", metavar="FILE", help="also write the service's answer as JSON")


def text_out(args):
    """Where a command prints its lines: stderr when --json names this process's stdout (the JSON there is the JSON
    alone, as audit's CSV is), else stdout."""
    return sys.stderr if args.json and is_stdout(args.json) else sys.stdout


def request(args, method: str, path: str, body: dict | None = None, *, answers: tuple[int, ...] = ()) -> dict | list:
    """One REST call; every failure is one line (InputError), with the service's own `detail`. A status in
    `answers` is an answer, not a failure (/readyz's 503 says which part is failing): its body is returned."""
    headers = {"Accept": "application/json"}
    if args.token_file:
        try:
            headers["Authorization"] = "Bearer " + Path(args.token_file).read_text().strip()
        except OSError as exc:
            raise InputError(f"--token-file {args.token_file}: {exc.strerror}") from None
        except UnicodeDecodeError:
            raise InputError(f"--token-file {args.token_file}: not a token (not text)") from None
    data = None
    if body is not None:
        data, headers["Content-Type"] = json.dumps(body).encode(), "application/json"
    url = args.url.rstrip("/") + path
    try:
        with urllib.request.urlopen(urllib.request.Request(url, data, headers, method=method), timeout=30) as resp:
            return json.loads(resp.read())
    except urllib.error.HTTPError as exc:
        try:
            answer = json.loads(exc.read())
        except ValueError:  # a proxy's HTML page, say
            answer = None
        if exc.code in answers and answer is not None:
            return answer
        detail = answer.get("detail", "") if isinstance(answer, dict) else ""
        if isinstance(detail, list):  # FastAPI's validation errors: where and what
            detail = "; ".join(f"{'.'.join(str(x) for x in d.get('loc', [])[1:])}: {d.get('msg')}" for d in detail)
        # the service's own 401 names `encoder-fleet token create`: the option is what the command adds
        hint = "; pass --token-file FILE" if exc.code == 401 and not args.token_file else ""
        raise InputError(f"{method} {path}: {exc.code} {detail or exc.reason}{hint}") from None
    except (urllib.error.URLError, OSError) as exc:
        raise InputError(f"{url}: cannot reach the service ({getattr(exc, 'reason', exc)})") from None
    except ValueError as exc:  # urllib's "unknown url type", or an answer that is not JSON
        raise InputError(f"{url}: {exc} (--url is the service's REST address, e.g. http://127.0.0.1:8000)") from None
