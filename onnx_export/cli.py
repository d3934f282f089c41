"""The command line that reproduces a run, for model cards: one renderer for every training script;
the argument types and the resume check the training scripts share.

Checkpoints store their argparse arguments, some as the values themselves and some as ``str(v)``
(a list of paths becomes ``"[PosixPath('a')]"``, a list of numbers ``"[1, 2]"``, a missing option
``"None"``); both render as arguments the script's parser accepts: unset options are left out, true
flags are bare, lists are space-separated.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path, PurePath

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
        quoted = _PATH_ITEM.findall(m.group(1))
        if quoted:  # paths or strings: what the quotes hold
            return [a or b for _, a, _, b in quoted]
        return [x.strip() for x in m.group(1).split(",") if x.strip()]  # numbers: "[1, 2]"
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


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1 (a count of steps, chunks, directions...)."""
    return _int_at_least(text, 1, "a positive integer")


def nonnegative_int(text: str) -> int:
    """argparse type: an integer >= 0 (where 0 means "all" or "off")."""
    return _int_at_least(text, 0, "an integer >= 0")


def _int_at_least(text: str, lo: int, what: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}") from None
    if v < lo:
        raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}")
    return v


def check_resume(stored: dict, current: dict, free, ckpt: Path) -> None:
    """Refuse to resume checkpoint ``ckpt`` (its stored arguments ``stored``) with other arguments than it
    was trained with: a ``ValueError`` naming the first differing flag. Flags in ``free`` may change (more
    steps, logging); flags the checkpoint does not record (added since) are not compared. Values compare
    as they render (``command_line``), so a checkpoint storing ``str(v)`` compares like one storing ``v``."""
    for k, v in current.items():
        if k in free or k not in stored:
            continue
        if _values(stored[k]) != _values(v):
            flag = f"--{k.replace('_', '-')}"
            may = ", ".join(f"--{f.replace('_', '-')}" for f in sorted(free))
            raise ValueError(
                f"{ckpt} was trained with {flag} {_shown(stored[k])}, this run asks for {flag} {_shown(v)}: resume "
                f"with the arguments it was started with (only {may} may change), or train into another --out"
            )


def _shown(v) -> str:
    """An argument's value as the message of ``check_resume`` shows it."""
    vals = _values(v)
    if vals is None:
        return "(not given)"
    return " ".join(vals) if vals else "(given)"
