"""Paths given by a user: why one cannot be read, and whether an output would overwrite an input."""

from __future__ import annotations

import errno
import os
from collections.abc import Iterable
from pathlib import Path

from vi3_core.errors import DataError


def missing_reason(path: str | Path) -> str:
    """Why ``path`` cannot be opened as a file, for a message after its name: a symbolic link that points to itself
    (a loop) or to a target that does not exist (naming it), a folder, or "does not exist"."""
    path = Path(path)
    if path.is_symlink():
        try:
            os.stat(path)
        except OSError as err:
            if err.errno == errno.ELOOP:
                return "is a symbolic link that points to itself (a loop)"
            return f"is a symbolic link to {os.readlink(path)}, which does not exist"
    if path.is_dir():
        return "is a folder, not a file"
    return "does not exist"


def _relation(output: str | Path, given: str | Path) -> str | None:
    """How ``output`` stands to the input ``given`` (symbolic links resolved, so another name of the same file
    counts): "is", "is inside", "contains", or None when they are apart."""
    out, inp = _real(output), _real(given)
    if out == inp:
        return "is"
    if inp in out.parents:
        return "is inside"
    if out in inp.parents:
        return "contains"
    return None


def check_apart(output: str | Path, inputs: Iterable[str | Path], *, what: str,
                relations: tuple[str, ...] = ("is", "is inside", "contains")) -> None:
    """DataError when ``output`` (named ``what`` in the message, e.g. "replay output") stands in one of
    ``relations`` (those that would destroy an input for this kind of output) to one of ``inputs``: writing it would
    destroy that input, whatever ``--force`` says."""
    for given in inputs:
        how = _relation(output, given)
        if how in relations:
            raise DataError(f"{what} {output} {how} the input {given}; writing it would destroy the input: choose an "
                            "output outside the inputs")


def check_output_file(output: str, inputs: Iterable[str | Path], *, what: str, kind: str, force: bool,
                      empty_hint: str = "") -> Path:
    """The file ``output`` a command is about to write, checked as every such output is: DataError (``what``: the
    option as messages name it, e.g. "vi3 calib --output"; ``kind``: what it holds, e.g. "a YAML file";
    ``empty_hint``: added to the empty name's message) for an empty name, an input it would destroy
    (``check_apart``), a folder, an existing file without ``force``, or a folder that does not exist."""
    if not output.strip():
        raise DataError(f"{what} {output!r}: an empty name; name {kind}{empty_hint}")
    out = Path(output)
    check_apart(out, inputs, what=what)
    if out.is_dir():
        raise DataError(f"{what} {out}: is a folder; name {kind}")
    if out.exists() and not force:
        raise DataError(f"{what} {out}: exists; pass --force to replace it")
    if not out.parent.is_dir():
        raise DataError(f"{what} {out}: its folder does not exist")
    return out


def _real(path: str | Path) -> Path:
    """``path`` absolute with every symbolic link resolved as far as they lead (a loop or a missing target stops
    there, without an error)."""
    return Path(os.path.realpath(path))
