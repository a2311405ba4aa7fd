"""`blendsplat keys create|list|revoke`: API keys in the service database (service/access/keys.py), managed by
whoever can reach that database (an operator, a Kubernetes Job): no key is needed to run it, and it never goes over
the API.

A key is printed once, when it is created. A revoked key stops working at once on the replica that serves the
next request after its cache entry expires (at most ``service.access.auth.CACHE_SECONDS``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def _key_store(args: argparse.Namespace):
    from ..settings import Settings
    from .keys import KeyStore

    overrides = {k: v for k, v in (("data_dir", args.data_dir), ("jobs_url", args.jobs_url)) if v is not None}
    return KeyStore.open(Settings(**overrides).jobs_database_url)


def cmd_keys(args: argparse.Namespace) -> int:
    from ..errors import ServiceError
    from .auth import TRUSTED, Access

    keys = _key_store(args)
    try:
        if args.keys_command == "create":
            key, token = keys.create(args.tenant, args.scope, args.name or "")
            Access.audit(TRUSTED, "key.create", key.id, key_tenant=key.tenant, scopes=",".join(key.scopes))
            if args.json:
                print(json.dumps({**key.as_json(), "key": token}))
            else:
                print(token)
                print(f"key {key.id}: tenant {key.tenant}, scopes {' '.join(key.scopes)} (shown once: store it now)",
                      file=sys.stderr)
        elif args.keys_command == "list":
            listed = keys.list(tenant=args.tenant, include_revoked=args.all)
            if args.json:
                print(json.dumps([k.as_json() for k in listed]))
            else:
                for k in listed:
                    state = "active" if k.active else f"revoked {k.revoked_at:%Y-%m-%d %H:%M}"
                    print(f"{k.id}  {k.tenant:<20} {' '.join(k.scopes):<30} {state}  {k.name}")
        else:
            key = keys.revoke(args.key_id)
            Access.audit(TRUSTED, "key.revoke", key.id, key_tenant=key.tenant)
            print(json.dumps(key.as_json()) if args.json else f"key {key.id} revoked")
    except ServiceError as e:
        print(f"blendsplat: error: {e}", file=sys.stderr)
        return 2
    finally:
        keys.close()
    return 0


def add_parser(commands) -> None:
    from .keys import SCOPE_HELP, SCOPES

    k = commands.add_parser("keys", help="create, list and revoke API keys (in the job database)",
                            description=__doc__.split("\n\n")[0])
    sub = k.add_subparsers(dest="keys_command", required=True, metavar="{create,list,revoke}")
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--data-dir", type=Path, default=None, help="data dir of the default SQLite job database")
    common.add_argument("--jobs-url", default=None, help="job database URL (default BLENDSPLAT_JOBS_URL)")
    common.add_argument("--json", action="store_true", help="JSON on stdout")
    c = sub.add_parser("create", parents=[common], help="a new key (printed once)")
    c.add_argument("--tenant", required=True, help="the tenant it acts for (lower-case letters, digits, . _ -)")
    c.add_argument("--scope", action="append", choices=SCOPES, required=True,
                   help="; ".join(f"{s}: {h}" for s, h in SCOPE_HELP.items()) + " (repeat for several)")
    c.add_argument("--name", help="what it is for (shown in lists)")
    ls = sub.add_parser("list", parents=[common], help="keys (never their secrets)")
    ls.add_argument("--tenant", help="only this tenant's")
    ls.add_argument("--all", action="store_true", help="include revoked keys")
    r = sub.add_parser("revoke", parents=[common], help="revoke a key by its id")
    r.add_argument("key_id", help="the key's id (bsk_<id>_..., or from `keys list`)")
    k.set_defaults(fn=cmd_keys)
