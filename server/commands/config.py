"""``mocap config show TAKE|FILE``: the settings in force for a take (or given by one Config.toml,
as ``mocap fit --config FILE`` takes them), and where each came from."""
from __future__ import annotations

from pathlib import Path

from common.errors import UserError
from server.config import PRESET_KEYS, SCHEDULES_KEY, SECTIONS, SETTINGS, load_config, toml_value
from server.project import check_recordings, config_key_note, plan_lines, plan_take
from server.takes import config_files, is_take, take_config


def register(sub) -> None:
    p = sub.add_parser("config", help="show the Config.toml settings in force for a take")
    action = p.add_subparsers(dest="config_command", metavar="ACTION")
    action.required = True
    show = action.add_parser("show", help="every setting, its value and the file it came from")
    show.add_argument("take", type=Path, metavar="TAKE|FILE",
                      help="take (or project) folder, or one Config.toml (as mocap fit --config FILE reads it)")
    show.set_defaults(func=run_show)
    keys = action.add_parser("keys", help="every key that a Config.toml may hold, with its meaning")
    keys.set_defaults(func=run_keys)


def run_show(args) -> int:
    if args.take.is_file():  # one file, over the defaults
        print(f"{args.take}: over the defaults")
        print("\n".join(load_config([args.take]).lines()))
        return 0
    if not args.take.is_dir():  # else a typo would show the defaults as if they were the take's
        raise UserError(f"{args.take}: no such folder or file")
    files = [str(p) for p in config_files(args.take) if p.is_file()]
    print(f"{args.take}: {', '.join(files) if files else 'no Config.toml; all defaults'}")
    print("\n".join(take_config(args.take).lines()))
    if is_take(args.take):  # what mocap run would read under these settings, checked as it checks them
        try:
            plan = plan_take(args.take)
            check_recordings(plan)
            print("\n".join(f"take: {line}" for line in plan_lines(plan)))
        except UserError as exc:
            print(f"take: mocap run would refuse it: {exc}{config_key_note(str(exc))}")
    return 0


def run_keys(args) -> int:
    # a Config.toml of every key at its default: each section's keys under its header; the keys a
    # preset sets commented out, so that the file, saved and given a preset, still takes it
    print("# every key a Config.toml may hold, at its default; the [fit] keys a preset sets are\n"
          "# commented out: set here, they are in force whatever the preset; so are the schedules,\n"
          "# which [fit.schedules.NAME] tables set (mocap config show prints those in force)")
    for section in SECTIONS:
        print(f"\n[{section}]")
        for s in SETTINGS:
            if s.section == section:
                mark = "# " if (s.section, s.key) in PRESET_KEYS | {SCHEDULES_KEY} else ""
                print(f"{mark}{s.key} = {toml_value(s.default)}   # {s.help}")
    return 0
