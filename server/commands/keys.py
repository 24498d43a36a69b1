"""mocap keys: make a CURVE key folder for an authenticated cluster."""
from __future__ import annotations

from pathlib import Path

from common.errors import UserError


def register(sub) -> None:
    p = sub.add_parser("keys", help="make CURVE keys: a server pair and an allow-list of client keys")
    p.add_argument("directory", type=Path)
    p.add_argument("--clients", default="client", help="comma-separated client names (default: client)")
    p.set_defaults(func=run)


def run(args) -> int:
    from server.trust import create_curve_keys

    names = tuple(n.strip() for n in args.clients.split(",") if n.strip())
    if not names:
        raise UserError("--clients: give at least one name")
    if (args.directory / "server.key_secret").exists():
        raise UserError(f"{args.directory}: already holds keys; refusing to overwrite them")
    create_curve_keys(args.directory, names)
    print(f"keys in {args.directory}: server.key_secret (server only), server.key, clients/*.key (allow-list), "
          f"client.key_secret (give clients a copy of the folder without server.key_secret)")
    return 0
