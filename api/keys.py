"""Administer API keys from the command line (needs access to the database, not to the API).

``python -m api.keys create NAME``   create a key and print it (it is not shown again)
``python -m api.keys list``          list keys (prefix, name, created, revoked)
``python -m api.keys revoke ID``     revoke a key by id
"""

from __future__ import annotations

import argparse

from sqlalchemy import select

from api.db import session_scope, utcnow
from api.migrate import upgrade
from api.models import ApiKey
from api.security import create_key
from api.settings import get_settings


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m api.keys", description="Administer API keys")
    sub = parser.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("create", help="create a key and print it once")
    c.add_argument("name", help="who the key is for")
    sub.add_parser("list", help="list keys")
    r = sub.add_parser("revoke", help="revoke a key")
    r.add_argument("key_id")
    args = parser.parse_args(argv)

    url = get_settings().resolved_database_url
    upgrade(url)
    with session_scope(url) as session:
        if args.cmd == "create":
            row, plain = create_key(session, args.name)
            print(f"id:             {row.id}")
            print(f"name:           {row.name}")
            print(f"api key:        {plain}")
            print(f"webhook secret: {row.webhook_secret}")
            print("Keep the key: only its hash is stored. Send it in the X-API-Key header.")
        elif args.cmd == "list":
            for row in session.scalars(select(ApiKey).order_by(ApiKey.created_at)):
                state = f"revoked {row.revoked_at:%Y-%m-%d}" if row.revoked_at else "active"
                print(f"{row.id}  {row.key_prefix}...  {row.name!r}  created {row.created_at:%Y-%m-%d %H:%M}  {state}")
        else:
            found = session.get(ApiKey, args.key_id)
            if found is None:
                print(f"no key with id {args.key_id}")
                return 1
            found.revoked_at = utcnow()
            print(f"revoked {found.id} ({found.name})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
