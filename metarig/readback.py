"""Reading back a file the project wrote itself (a run record, a results file, a cache).

Such a file can still be found damaged: cut short by a full disk, a copy stopped half-way, a
crash outside the project's atomic writes. Reading it must then end the command in one line
that names the file and says what the user can do, and must leave the file as it is (the
caller refuses before it writes anything). `read_json` and `read_npz` turn every way a read can
fail (missing file, truncated zip, bad JSON, bytes that are not text, a missing key) into one
`DamagedFileError`, a `ValueError`, so the commands' usual error path reports it.
"""

import json
import zipfile
import zlib
from pathlib import Path

import numpy as np

RESTORE = "restore it from a copy, or start anew in another folder"
WRITE_AGAIN = "write it again with the command that made it"

# what np.load / zipfile / json raise on a cut or garbled file
READ_ERRORS = (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile, zlib.error)


class DamagedFileError(ValueError):
    """A file this project wrote that cannot be read back (the message names the file, the
    problem and what to do)."""


def damaged(path: str | Path, what: str, problem: str, remedy: str = RESTORE) -> DamagedFileError:
    """The one-line error for `path` (a `what`, e.g. "design-run checkpoint")."""
    problem = str(problem).splitlines()[0] if str(problem) else "unreadable"
    return DamagedFileError(f"{path}: damaged or unreadable {what} ({problem}); {remedy}")


def read_json(path: str | Path, what: str, remedy: str = RESTORE, kind: type = dict):
    """The parsed JSON document of `path`, which must be a `kind` (dict by default).

    Raises:
        DamagedFileError: the file cannot be read, is not JSON, or is not a `kind`.
    """
    try:
        doc = json.loads(Path(path).read_text())
    except READ_ERRORS as exc:
        raise damaged(path, what, getattr(exc, "strerror", None) or exc, remedy) from None
    if not isinstance(doc, kind):
        raise damaged(path, what, f"a JSON {type(doc).__name__}, not a {kind.__name__}", remedy)
    return doc


def read_npz(path: str | Path, keys: tuple[str, ...], what: str, remedy: str = RESTORE,
             optional: tuple[str, ...] = ()) -> dict[str, np.ndarray]:
    """The arrays `keys` (and those of `optional` that it holds) of the `.npz` file `path`, read
    into memory (no pickles).

    Raises:
        DamagedFileError: the file cannot be read, is not a readable `.npz`, or lacks a key.
    """
    try:
        with np.load(path, allow_pickle=False) as f:
            missing = [k for k in keys if k not in f.files]
            if missing:
                raise damaged(path, what, f"no {', '.join(missing)} in it", remedy)
            return {k: np.asarray(f[k]) for k in (*keys, *optional) if k in f.files}
    except DamagedFileError:
        raise
    except READ_ERRORS as exc:
        raise damaged(path, what, getattr(exc, "strerror", None) or exc, remedy) from None


__all__ = ["READ_ERRORS", "RESTORE", "WRITE_AGAIN", "DamagedFileError", "damaged", "read_json",
           "read_npz"]
