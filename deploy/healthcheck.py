#!/usr/bin/env python3
"""Container health of ``mocap server``: is a socket listening on port MOCAP_PORT (default 5555)?

Reads the kernel's socket tables instead of connecting: a bare TCP connection is no ZeroMQ
peer, and the server would log and count every probe as a dropped handshake. Exit 0: healthy.
"""
import os
import sys

LISTEN = "0A"  # TCP state in /proc/net/tcp*


def listening(port: int) -> bool:
    suffix = f":{port:04X}"
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            with open(table) as f:
                rows = [line.split() for line in f.readlines()[1:]]
        except OSError:
            continue
        if any(len(r) > 3 and r[1].endswith(suffix) and r[3] == LISTEN for r in rows):
            return True
    return False


if __name__ == "__main__":
    sys.exit(0 if listening(int(os.environ.get("MOCAP_PORT", "5555"))) else 1)
