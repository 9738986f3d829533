"""`lidar-outliers users add|list|revoke`: API keys of the job service.

Acts on the database the API uses: ``DATABASE_URL``, else the SQLite file under ``DATA_DIR``
(default ``./data`` in the project root), the same one `make run` uses. Its schema is migrated
first when it is older than this version. ``add`` prints the new key alone on the last line so
scripts can capture it: ``KEY=$(lidar-outliers users add alice | tail -n 1)``.
"""

from __future__ import annotations

import argparse
import sys

import sqlalchemy as sa

from lidar_outliers.jobs.database import describe, normalise_url, sqlite_file
from lidar_outliers.jobs.settings import get_settings
from lidar_outliers.jobs.store import Store, StoreError


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "users", help="manage API keys of the job service",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    actions = parser.add_subparsers(dest="users_action", required=True, metavar="ACTION")
    add = actions.add_parser("add", help="create a user and print its new key (last line)")
    add.add_argument("name")
    actions.add_parser("list", help="list users (names and dates; keys are not stored)")
    revoke = actions.add_parser("revoke", help="invalidate a user's key")
    revoke.add_argument("name")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    settings = get_settings()
    sqlite = sqlite_file(normalise_url(settings.database_url))
    new_store = sqlite is not None and not sqlite.exists()
    try:
        store = Store(settings.database_url)
        if new_store:  # the likely mistake: a service running with another DATA_DIR
            print(f"lidar-outliers: note: no store existed at {sqlite}, a new one was made; a "
                  "service started with another DATA_DIR or DATABASE_URL will not know its "
                  "keys: set the same ones here", file=sys.stderr)
        if args.users_action == "add":
            user, key = store.add_user(args.name)
            print(f"wrote key for {user.name!r} to {store.describe()}; a service finds it "
                  "with the same DATA_DIR (or DATABASE_URL). The key (shown only once) is on "
                  "the next line:")
            print(key, flush=True)
        elif args.users_action == "list":
            for user in store.list_users():
                state = f"revoked {user.revoked}" if user.revoked else "active"
                name = user.name.split("#revoked-")[0]
                print(f"{name}\tcreated {user.created}\t{state}")
        elif args.users_action == "revoke":
            store.revoke_user(args.name)
            print(f"revoked {args.name!r}")
    except StoreError as exc:
        print(f"lidar-outliers: error: {exc}", file=sys.stderr)
        return 1
    except sa.exc.OperationalError as exc:  # unreachable server, wrong password, ...
        reason = str(exc.orig).strip().splitlines()[0] if exc.orig else str(exc)
        print(f"lidar-outliers: error: the database {describe(settings.database_url)} cannot "
              f"be used: {reason}", file=sys.stderr)
        return 1
    return 0
