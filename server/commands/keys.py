"""mocap keys: make a CURVE key folder for an authenticated cluster."""
from __future__ import annotations

from pathlib import Path

from common.errors import UserError


def register(sub) -> None:
    p = sub.add_parser("keys", help="make CURVE keys: a server pair and an allow-list of client keys")
    p.add_argument("directory", type=Path,
                   help="folder to make the keys in (made if missing; one that holds keys already is refused)")
    p.add_argument("--clients", default="client", help="comma-separated client names (default: client)")
    p.set_defaults(func=run)


def run(args) -> int:
    from server.trust import CLIENT_FOLDER, check_client_names, create_curve_keys

    names = tuple(n.strip() for n in args.clients.split(","))
    check_client_names(names)  # before anything is made: a refused name leaves no half-made folder
    if args.directory.exists() and not args.directory.is_dir():
        raise UserError(f"{args.directory}: is a file; name a folder")
    # any key: a server's folder, its clients/ allow-list, a client's own folder
    held = sorted(p.name for p in args.directory.glob("*.key*")) if args.directory.is_dir() else []
    if held:
        raise UserError(f"{args.directory}: already holds keys ({', '.join(held[:3])}{', ...' if len(held) > 3 else ''}); "
                        "refusing to make more there: give a new folder")
    create_curve_keys(args.directory, names)
    folders = ", ".join(CLIENT_FOLDER.format(name=n) + "/" for n in names)
    print(f"keys in {args.directory}: server.key_secret (the server's only), server.key, clients/*.key (the "
          f"allow-list); copy each client its own folder ({folders}) and start it with --curve-keys FOLDER")
    return 0
