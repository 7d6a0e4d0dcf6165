"""coopctl key: make the swarm key every vehicle of a swarm shares (docs/sharing.md, "Swarm key").

    coopctl key generate --out /etc/coopd/swarm.key     # 32 random bytes as "hex:...", mode 0600

The file holds one line, `hex:` and 64 hex digits, the format the daemon's sharing.swarm_key_file
reads (coopd.sharing.swarmkey.read_key_file, the same decoder `coopctl key check` uses).
"""

import os
from pathlib import Path

from coopd.sharing import swarmkey

from .output import OK, about_file, add_json_option, emit

KEY_BYTES = 32


def register(subparsers) -> None:
    """Add the `key` command group to coopctl."""
    p = subparsers.add_parser("key", help="make or check the swarm key file")
    sub = p.add_subparsers(dest="key_command", metavar="SUBCOMMAND", required=True)
    gen = sub.add_parser("generate", help=f"write a new random {KEY_BYTES}-byte swarm key (mode 0600)")
    gen.add_argument("--out", type=Path, required=True, help="the key file to create")
    gen.add_argument("--force", action="store_true", help="replace an existing file")
    add_json_option(gen)
    gen.set_defaults(handler=run_generate)
    check = sub.add_parser("check", help="read a key file as the daemon does; print its length")
    check.add_argument("file", type=Path)
    add_json_option(check)
    check.set_defaults(handler=run_check)


def key_file_text(key: bytes) -> str:
    """The key file's content for `key`."""
    return f"hex:{key.hex()}\n"


def run_generate(args) -> int:
    """Create the key file with mode 0600 (never readable by others, not even for a moment), whatever
    the umask: unlike map exports, a key file is a secret."""
    flags = os.O_WRONLY | os.O_CREAT | (os.O_TRUNC if args.force else os.O_EXCL)
    fd = os.open(args.out, flags, 0o600)
    try:
        os.fchmod(fd, 0o600)  # also when --force replaced a file with other permissions
        os.write(fd, key_file_text(os.urandom(KEY_BYTES)).encode("ascii"))
        os.fsync(fd)
    finally:
        os.close(fd)
    emit(args, {"file": str(args.out), "key_bytes": KEY_BYTES, "mode": "0600"},
         f"swarm key written to {args.out} (mode 0600); copy it to every vehicle of the swarm and set "
         f"[sharing] swarm_key_file")
    return OK.code


def run_check(args) -> int:
    with about_file(args.file):
        key = swarmkey.read_key_file(args.file)
        if key is None:
            raise ValueError("holds no key")
    emit(args, {"file": str(args.file), "key_bytes": len(key)},
         f"{args.file}: a swarm key of {len(key)} bytes")
    return OK.code
