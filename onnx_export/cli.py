"""The command line that reproduces a run, for model cards: one renderer for every training script.

Checkpoints store their argparse arguments, some as the values themselves and some as ``str(v)``
(a list of paths becomes ``"[PosixPath('a')]"``, a missing option ``"None"``); both render as
arguments the script's parser accepts: unset options are left out, true flags are bare, lists
are space-separated.
"""

from __future__ import annotations

import re
from pathlib import PurePath

_PATH_LIST = re.compile(r"^\[(.*)\]$")
_PATH_ITEM = re.compile(r"""(?:PosixPath|WindowsPath|PurePosixPath)\((['"])(.*?)\1\)|(['"])(.*?)\3""")


def _values(v) -> list[str] | None:
    """The argument's values as strings, [] for a bare flag, None to leave it out."""
    if v is None or v is False or v in ("None", "False"):
        return None
    if v is True or v == "True":
        return []
    if isinstance(v, (list, tuple)):
        return [str(x) for x in v]
    if isinstance(v, PurePath):
        return [str(v)]
    text = str(v)
    m = _PATH_LIST.match(text)
    if m:
        return [a or b for _, a, _, b in _PATH_ITEM.findall(m.group(1))]
    return [text]


def command_line(prog: str, args: dict, skip=()) -> str:
    """``python -m prog --key value ...`` for the arguments ``args`` (argparse dests), without ``skip``."""
    parts = [f"python -m {prog}"]
    for k, v in args.items():
        if k in skip:
            continue
        vals = _values(v)
        if vals is None:
            continue
        parts.append(" ".join([f"--{k.replace('_', '-')}", *vals]))
    return " ".join(parts)
