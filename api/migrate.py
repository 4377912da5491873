"""Database migrations (Alembic, scripts in ``api/migrations/versions``).

``python -m api.migrate``            upgrade the configured database to the newest schema
``python -m api.migrate current``    print the revision the database is at
``python -m api.migrate revision -m "add x"``  autogenerate a new revision from api.models (developers)
"""

from __future__ import annotations

import argparse
from pathlib import Path

from alembic import command
from alembic.config import Config

from api.settings import get_settings

MIGRATIONS_DIR = Path(__file__).resolve().parent / "migrations"


def alembic_config(url: str | None = None) -> Config:
    """An Alembic config for ``url`` (default: the settings' database) without any .ini file."""
    cfg = Config()
    cfg.set_main_option("script_location", str(MIGRATIONS_DIR))
    cfg.attributes["url"] = url or get_settings().resolved_database_url
    return cfg


def upgrade(url: str | None = None, revision: str = "head") -> None:
    """Bring the database at ``url`` to ``revision``."""
    command.upgrade(alembic_config(url), revision)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m api.migrate", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="cmd")
    sub.add_parser("upgrade", help="upgrade to head (the default)")
    sub.add_parser("current", help="show the current revision")
    rev = sub.add_parser("revision", help="autogenerate a revision")
    rev.add_argument("-m", "--message", required=True)
    args = parser.parse_args(argv)
    cfg = alembic_config()
    if args.cmd in (None, "upgrade"):
        command.upgrade(cfg, "head")
        print(f"database at head: {cfg.attributes['url']}")
    elif args.cmd == "current":
        command.current(cfg, verbose=True)
    else:
        command.revision(cfg, message=args.message, autogenerate=True)


if __name__ == "__main__":
    main()
